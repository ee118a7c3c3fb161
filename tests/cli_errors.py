"""Helper of the CLI tests (not a test module): the one-line error contract of every refused input."""
from __future__ import annotations


def one_line(capsys, *needles: str) -> str:  # noqa: ANN001
    """The captured stderr: exactly one line starting ``error: `` and holding every one of ``needles``."""
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and err.startswith("error: "), err
    for n in needles:
        assert n in err, (n, err)
    return err
