"""Moving bytes between processes: Zenoh sessions and key names (bus), the hub, certificates, and the
payload planes that carry large arrays beside the messages. Knows nothing of operators or frames."""
