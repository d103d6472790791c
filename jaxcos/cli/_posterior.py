from ..inference._posterior import add_command  # noqa: F401  (temporary: moved here by the split)
