"""The dataflow engine: messages, the operator API, the bus and its payload rings, the runtime that
runs one operator, delivery (joining, acks, stats), the graph, the launcher, the hub and the MCAP log."""
