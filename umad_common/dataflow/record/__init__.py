"""The MCAP log: its format (writing and reading), the recorder that writes a run's log, and the
source that replays one."""
