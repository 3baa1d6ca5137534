"""What operators and graphs are: the message format, the operator classes and their context, pacing
parameters, plugin loading, `graph.yaml` and its parameter assignments, the exit codes."""
