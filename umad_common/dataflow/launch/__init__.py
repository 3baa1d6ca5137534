"""The whole graph: the launcher that starts the hub, the replicas and the recorder, its progress
report, and the hub's access rules derived from the graph."""
