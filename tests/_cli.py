"""The command line's one-line errors, as tests/test_certify_run.py and tests/test_export_cli.py check them."""

from __future__ import annotations

from d2spo import cli


def one_error_line(capsys, args) -> str:
    """``d2spo ARGS`` exits 2 with one line on stderr, ``d2spo: error: ...``: that line."""
    assert cli.main(args) == 2
    err = [ln for ln in capsys.readouterr().err.splitlines() if ln.strip()]
    assert len(err) == 1 and err[0].startswith("d2spo: error: "), err
    return err[0]
