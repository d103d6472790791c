"""The one exception users see for bad input."""


class InputError(ValueError):
    """Bad user input: a file, a field or an option that jaxcos cannot use.

    The message is one sentence that names the file (and line, where there is
    one) and the problem, e.g. ``data.csv, line 7: 'abc' in column 'r' is not a
    number.``. Every command turns it into that line on stderr and a non-zero
    exit status, without a traceback.
    """
