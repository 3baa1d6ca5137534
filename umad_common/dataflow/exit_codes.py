"""The exit codes of the dataflow's processes, which the launcher and the commands act on."""

EXIT_CONFIG = 3  # an operator that exits with this failed on its configuration: restarting cannot help
EXIT_INCOMPLETE = 4  # `umad launch` / `umad replay`: the graph finished, but its recorded log lacks messages
EXIT_STOPPED = 130  # stopped by Ctrl-C or SIGTERM (128 + SIGINT, the shell's convention)
