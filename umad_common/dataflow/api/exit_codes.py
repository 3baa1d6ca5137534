"""The exit codes of the dataflow's processes, which the launcher and the commands act on."""

EXIT_BAD_INPUT = 2  # a verb refused what it was given before starting anything (argparse's code for bad usage)
EXIT_CONFIG = 3  # an operator that exits with this failed on its configuration: restarting cannot help
EXIT_INCOMPLETE = 4  # `umad launch` / `umad replay`: the graph finished, but its recorded log lacks messages
EXIT_STOPPED = 130  # stopped by Ctrl-C or SIGTERM (128 + SIGINT, the shell's convention)
