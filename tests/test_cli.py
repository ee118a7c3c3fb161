"""The CLI turns usage and file-system errors into one line and exit code 2 (no traceback)."""
from __future__ import annotations

from mmslam.cli import main


def test_bad_option_value_is_a_usage_error(capsys):
    assert main(["slam", "nowhere", "--particles", "abc", "--out", "x"]) == 2
    err = capsys.readouterr().err
    assert "Traceback" not in err and "--particles" in err


def test_output_path_that_is_a_file(tmp_path, capsys):
    f = tmp_path / "afile"
    f.write_text("")
    assert main(["trace", "paper", "--source", "analytic", "--out", str(f), "--quiet"]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("error: ") and str(f) in err and "writable path" in err and "\n" not in err


def test_plot_into_missing_directory(tmp_path, capsys):
    assert main(["trace", "paper", "--source", "analytic", "--out", str(tmp_path / "c"), "--steps", "2",
                 "--quiet"]) == 0
    capsys.readouterr()
    bad = tmp_path / "missing" / "dir" / "toa.png"
    assert main(["paths", str(tmp_path / "c"), "--plot", str(bad)]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("error: ") and "missing" in err and "\n" not in err
