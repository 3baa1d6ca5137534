"""The built-in synthetic driving world (camera, lidar, actions, anomalies) in the AnoVox layout."""
