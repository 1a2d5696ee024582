"""Tasks: the registry (`make_env`), the paper's `avoid` and point-goal navigation `goal`."""
