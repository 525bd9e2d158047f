"""Fixtures shared by the core tests."""

import signal

import pytest


def _default_sigint():
    signal.signal(signal.SIGINT, signal.SIG_DFL)


@pytest.fixture
def default_sigint():
    """A ``preexec_fn`` for subprocesses that a test interrupts with SIGINT: in the child
    before exec, Ctrl-C's default action, which a shell that started this suite in the
    background (``make test &``) set to ignore, and Python then never turns into
    KeyboardInterrupt."""
    return _default_sigint
