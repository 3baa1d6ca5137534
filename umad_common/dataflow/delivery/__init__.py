"""Getting one operator its frames: joining inputs by `(run, seq)`, the live, ordered and replay paths,
the service messages (acks, resends, goodbyes) and the stats a replica publishes."""
