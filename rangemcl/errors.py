"""Errors raised for bad user input (as opposed to bugs, which raise anything else)."""

from __future__ import annotations


class InputError(ValueError):
    """Bad input from a user: a file, a config, a scan or a mesh that cannot be used.

    The message is one line that names the thing (file, key, array) and what is wrong with it; the CLIs
    print it without a traceback and exit with status 2.
    """
