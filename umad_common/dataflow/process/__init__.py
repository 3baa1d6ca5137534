"""One operator replica as a process: its entry point, the runtime that connects it to the bus, the
frame processor, the source driver, live control and the allocator settings."""
