"""User-facing errors.

Anything raised as :class:`MatcapError` (or ``ValueError`` / ``OSError`` from the lower packages) is printed by
the CLI as one line and ends the process with exit code 2; it never shows a traceback (set ``MATCAP_DEBUG=1``
to see one).
"""


class MatcapError(Exception):
    """A problem with the user's input or environment, explained in one line."""
