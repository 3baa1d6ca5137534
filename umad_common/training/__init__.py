"""Training loops, one file per model; models themselves live in umad_common.models."""
