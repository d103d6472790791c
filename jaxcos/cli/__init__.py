"""The ``jaxcos`` command line: the top layer, thin over the library."""

from ._main import main
