"""The one exception users see for bad input."""

import os


class InputError(ValueError):
    """Bad user input: a file, a field or an option that jaxcos cannot use.

    The message is one sentence that names the file (and line, where there is
    one) and the problem, e.g. ``data.csv, line 7: 'abc' in column 'r' is not a
    number.``. Every command turns it into that line on stderr and a non-zero
    exit status, without a traceback.
    """


def refuse_overwrite(paths, force):
    """Raise :class:`InputError` if any of ``paths`` exists and ``force`` is off."""
    for path in paths:
        if os.path.exists(path) and not force:
            raise InputError(f"{path}: already exists; pass --force to overwrite it.")
