"""Tasks: the registry (`make_env`) and the tasks that ship (`avoid`, the paper's)."""
