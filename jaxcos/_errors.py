"""The one exception users see for bad input, and how results are written without overwriting or half-writing."""

import contextlib
import os
import shutil
import tempfile


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


@contextlib.contextmanager
def staged_outputs(out_dir, names, force):
    """Write the files ``names`` of a result folder ``out_dir`` together.

    Refuses to overwrite them unless ``force`` (:func:`refuse_overwrite`), then
    yields a temporary folder inside ``out_dir`` to write them into; they are
    moved into ``out_dir`` only when the block ends without error. On an error
    nothing is moved, and ``out_dir`` is removed again if this call created it
    and it is still empty.
    """
    out_dir = os.fspath(out_dir)
    refuse_overwrite([os.path.join(out_dir, name) for name in names], force)
    created = not os.path.isdir(out_dir)
    os.makedirs(out_dir, exist_ok=True)
    try:
        with tempfile.TemporaryDirectory(dir=out_dir, prefix=".jaxcos-") as tmp:
            yield tmp
            for name in names:
                shutil.move(os.path.join(tmp, name), os.path.join(out_dir, name))
    except BaseException:
        if created and not os.listdir(out_dir):
            os.rmdir(out_dir)
        raise
