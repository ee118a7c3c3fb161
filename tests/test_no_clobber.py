"""Issue 25: ``--force`` never deletes or overwrites anything mmslam did not write.

The policy (:mod:`mmslam.outputs`, README "Exit codes, outputs and interruptions"): a writing
command uses an existing target only if it is empty or its own previous output of the same kind
(marker ``.mmslam-output.json`` for folders, mmslam's tag in figures and ``.npz`` files); a user's
folder or file, or what a symbolic link points to, is refused with one line and exit 2, with or
without ``--force``. Each test hashes the user's tree before and after.
"""
from __future__ import annotations

import hashlib
import json
import os
from pathlib import Path

import pytest

from mmslam.cli import main
from cli_errors import one_line

TRACE = ["trace", "paper", "--source", "analytic", "--steps", "2", "--quiet"]


def tree(root: Path) -> dict[str, str]:
    """Every entry under ``root`` (not following links): file -> sha256, link -> 'link:target', dir -> 'dir'."""
    out = {}
    for dirpath, dirnames, filenames in os.walk(root):
        for name in dirnames + filenames:
            p = Path(dirpath) / name
            rel = str(p.relative_to(root))
            if p.is_symlink():
                out[rel] = "link:" + os.readlink(p)
            elif p.is_dir():
                out[rel] = "dir"
            else:
                out[rel] = hashlib.sha256(p.read_bytes()).hexdigest()
    return out


@pytest.fixture(scope="module")
def cache(tmp_path_factory) -> Path:
    root = tmp_path_factory.mktemp("cache")
    assert main(TRACE + ["--out", str(root)]) == 0
    (d,) = [p for p in root.iterdir() if p.is_dir()]
    return d


def fake_root(tmp_path: Path) -> Path:
    root = tmp_path / "root"
    (root / "etc").mkdir(parents=True)
    (root / "etc" / "passwd").write_text("root:x:0:0::/root:/bin/sh\n")
    (root / "bin").mkdir()
    (root / "bin" / "sh").write_bytes(b"\x7fELF")
    (root / "thesis.tex").write_text("\\documentclass{article}")
    return root


# ============================================================ 1. slam --force deleted any folder
@pytest.mark.parametrize("force", [[], ["--force"]])
def test_slam_never_deletes_a_user_folder(tmp_path, capsys, cache, force):
    # before: `slam CACHE --out DIR --force` renamed DIR aside and deleted it (thesis.tex, etc/passwd, bin)
    root = fake_root(tmp_path)
    before = tree(tmp_path)
    capsys.readouterr()
    assert main(["slam", str(cache), "--particles", "3", "--steps", "2", "--out", str(root), *force]) == 2
    one_line(capsys, str(root), "did not write")
    assert tree(tmp_path) == before


def test_slam_replaces_only_a_previous_result_holding_nothing_else(tmp_path, capsys, cache):
    out = tmp_path / "res"
    argv = ["slam", str(cache), "--particles", "3", "--steps", "2", "--out", str(out)]
    assert main(argv) == 0 and main(argv) == 0  # a previous result is replaced
    (out / "notes.txt").write_text("my notes")  # ... but not once the user put a file of theirs in it
    before = tree(tmp_path)
    for force in ([], ["--force"]):
        capsys.readouterr()
        assert main(argv + force) == 2
        one_line(capsys, str(out), "notes.txt")
        assert tree(tmp_path) == before
    (out / "notes.txt").unlink()
    assert main(argv) == 0


def test_slam_follows_a_link_and_keeps_it(tmp_path, capsys, cache):
    real = tmp_path / "real"
    argv = ["slam", str(cache), "--particles", "3", "--steps", "2", "--out"]
    assert main(argv + [str(real)]) == 0
    link = tmp_path / "link"
    link.symlink_to(real)
    old_meta = (real / "meta.json").read_bytes()
    assert main(argv + [str(link), "--force"]) == 0  # a link to a previous result: the result is replaced
    assert link.is_symlink() and os.readlink(link) == str(real) and (real / "meta.json").read_bytes() != old_meta
    user = fake_root(tmp_path / "u")
    link2 = tmp_path / "link2"
    link2.symlink_to(user)
    before = tree(tmp_path)
    for force in ([], ["--force"]):
        capsys.readouterr()
        assert main(argv + [str(link2), *force]) == 2
        one_line(capsys, str(link2), "did not write")
        assert tree(tmp_path) == before


def test_trace_force_touches_only_its_own_cache(tmp_path, capsys, cache):
    root = fake_root(tmp_path)
    before = tree(tmp_path)
    capsys.readouterr()
    assert main(TRACE + ["--out", str(root), "--force"]) == 2  # before: the cache was added to the user's folder
    one_line(capsys, str(root), "did not write")
    assert tree(tmp_path) == before
    # a folder with the cache's name holding a user's file: not deleted by --force
    croot = tmp_path / "c"
    assert main(TRACE + ["--out", str(croot)]) == 0
    (cdir,) = [p for p in croot.iterdir() if p.is_dir()]
    (cdir / "notes.txt").write_text("mine")
    before = tree(tmp_path)
    capsys.readouterr()
    assert main(TRACE + ["--out", str(croot), "--force"]) == 2
    one_line(capsys, str(cdir), "not a cache mmslam wrote")
    assert tree(tmp_path) == before
    (cdir / "notes.txt").unlink()
    m = json.loads((cdir / "manifest.json").read_text())
    assert main(TRACE + ["--out", str(croot), "--force"]) == 0  # its own cache: re-traced
    assert json.loads((cdir / "manifest.json").read_text())["steps_completed"] == m["steps_completed"]


# ============================================================ 2. scene streets overwrote --out and --data unchecked
def test_scene_streets_refuses_user_files_and_replaces_its_own(tmp_path, capsys, cache):
    # before: `scene streets ... --out user.png --data user.npz` overwrote both (no check, no --force)
    import numpy as np

    user = tmp_path / "user"
    user.mkdir()
    png, npz = user / "user.png", user / "user.npz"
    png.write_bytes(b"\x89PNG my holiday photo")
    np.savez(npz, grid=np.arange(4))
    before = tree(tmp_path)
    args = ["scene", "streets", "sionna:simple_street_canyon"]
    for out, data in ((png, tmp_path / "new.npz"), (tmp_path / "new.png", npz)):
        capsys.readouterr()
        assert main(args + ["--out", str(out), "--data", str(data)]) == 2
        one_line(capsys, str(png if out == png else npz), "did not write")
        assert tree(tmp_path) == before
    mine_png, mine_npz = tmp_path / "s.png", tmp_path / "s.npz"
    assert main(args + ["--out", str(mine_png), "--data", str(mine_npz)]) == 0
    assert main(args + ["--out", str(mine_png), "--data", str(mine_npz), "--res", "4"]) == 0  # its own: replaced
    assert float(np.load(mine_npz)["res"]) == 4.0
    # an .npz of another mmslam command is refused with the right reason (it used to say "mmslam did not write")
    from mmslam.outputs import NPZ_TAG, check_npz_target

    before = tree(tmp_path)
    with pytest.raises(Exception, match="is an mmslam streets file, not a channel file") as e:
        check_npz_target(mine_npz, "channel")
    assert "\n" not in str(e.value) and "did not write" not in str(e.value) and tree(tmp_path) == before
    assert str(np.load(mine_npz)[NPZ_TAG]) == "streets"
    capsys.readouterr()
    assert main(["export", str(cache), "--cfr", "--subcarriers", "8", "--out", str(mine_npz)]) == 2
    one_line(capsys, str(mine_npz), "is an mmslam streets file, not a channel file")
    assert tree(tmp_path) == before


# ============================================================ 3. ablate --force --report replaced a user's summary/report/figure
ABLATE = ["ablate", "paper", "--source", "analytic", "--steps", "2", "--mc", "1", "--particles", "3",
          "--variants", "baseline", "--workers", "1", "--quiet", "--report"]


def user_results(folder: Path) -> None:
    """A user's files that happen to have the names an ablation writes."""
    import numpy as np

    folder.mkdir(parents=True, exist_ok=True)
    (folder / "summary.json").write_text('{"my": "summary"}')
    (folder / "summary.parquet").write_bytes(b"PAR1 not really")
    (folder / "report.html").write_text("<html><title>my report</title></html>")
    (folder / "figures").mkdir(exist_ok=True)
    (folder / "figures" / "fig2a_gospa_vs.png").write_bytes(b"\x89PNG my figure")
    np.save(folder / "data.npy", np.arange(3))


def test_ablate_force_report_never_replaces_a_users_files(tmp_path, capsys):
    # before: ablate --force --report into this folder replaced summary.json, summary.parquet, report.html
    # and figures/fig2a_gospa_vs.png, although its help said "nothing in it is deleted"
    user = tmp_path / "user"
    user_results(user)
    before = tree(tmp_path)
    for force in ([], ["--force"]):
        capsys.readouterr()
        assert main(ABLATE + force + ["--out", str(user)]) == 2
        one_line(capsys, str(user), "did not write")
        assert tree(tmp_path) == before


def test_an_ablation_folder_with_a_users_files_of_its_names_is_not_overwritten(tmp_path, capsys):
    # an ablation folder an older mmslam marked when writing into a user's folder with --force: the
    # user's files of the names an ablation writes are recognised by content and never overwritten
    out = tmp_path / "abl"
    assert main(ABLATE + ["--out", str(out)]) == 0
    keep = {p: p.read_bytes() for p in out.rglob("*") if p.is_file()}
    for name in ("summary.json", "summary.parquet", "report.html", "figures/fig2a_gospa_vs.png"):
        mine = out / name
        mine.write_bytes(b"the user's " + name.encode())
        before = tree(tmp_path)
        for argv in (["report", str(out)], ABLATE + ["--out", str(out)], ABLATE + ["--force", "--out", str(out)]):
            capsys.readouterr()
            assert main(argv) == 2, argv
            one_line(capsys, name.split("/")[-1], "not a file mmslam wrote")
            assert tree(tmp_path) == before
        mine.write_bytes(keep[mine])
    capsys.readouterr()
    assert main(["report", str(out)]) == 0  # its own files are rewritten


# ============================================================ acceptance: fault injection over every writing command
def user_area(root: Path) -> dict[str, Path]:
    """A user's things: a folder with files (and names an ablation writes), files, links to both."""
    import numpy as np

    root.mkdir(parents=True, exist_ok=True)
    folder = root / "thesis"
    user_results(folder)
    (folder / "thesis.tex").write_text("\\documentclass{article}")
    (folder / "meshes").mkdir()
    (folder / "meshes" / "bs.ply").write_text("ply\nmine")
    (folder / "manifest.json").write_text('{"mine": true}')
    tex = root / "thesis.tex"
    tex.write_text("\\documentclass{article}")
    png = root / "photo.png"
    png.write_bytes(b"\x89PNG my photo")
    gif = root / "cat.gif"
    gif.write_bytes(b"GIF89a my cat")
    npz = root / "data.npz"
    np.savez(npz, mine=np.arange(3))
    figdir = root / "figure.png"  # a folder with a figure's name
    figdir.mkdir()
    (figdir / "keep.txt").write_text("mine")
    links = {}
    for name, target in (("link_dir", folder), ("link_tex", tex), ("link_png", png), ("link_npz", npz),
                         ("link_gif", gif)):
        links[name] = root / name
        links[name].symlink_to(target)
    (root / "dangling.png").symlink_to(root / "nowhere" / "x.png")
    return {"folder": folder, "tex": tex, "png": png, "npz": npz, "gif": gif, "figdir": figdir,
            "dangling": root / "dangling.png", **links}


# command -> (argv with {out} for the target, targets it is run against, has --force)
DIR_TARGETS = ("folder", "tex", "link_dir", "link_tex")
FIG_TARGETS = ("png", "figdir", "link_png", "dangling")
NPZ_TARGETS = ("npz", "figdir", "link_npz", "tex")
GIF_TARGETS = ("gif", "link_gif")
COMMANDS = {
    "trace": (TRACE + ["--out", "{out}"], DIR_TARGETS, True),
    "slam": (["slam", "{cache}", "--particles", "3", "--steps", "2", "--out", "{out}"], DIR_TARGETS, True),
    "slam --animate": (["slam", "{cache}", "--particles", "3", "--steps", "2", "--out", "{fresh}", "--animate",
                        "{out}"], GIF_TARGETS, True),
    "ablate": (ABLATE + ["--out", "{out}"], DIR_TARGETS, True),
    "demo": (["demo", "--source", "analytic", "--mc", "1", "--particles", "3", "--workers", "1", "--quiet",
              "--out", "{out}"], DIR_TARGETS, True),
    "report": (["report", "{out}"], DIR_TARGETS, False),
    "scene build": (["scene", "build", "paper", "--out", "{out}"], DIR_TARGETS, True),
    "scene show": (["scene", "show", "paper", "--out", "{out}"], FIG_TARGETS, True),
    "scene coverage": (["scene", "coverage", "canyon", "--out", "{out}"], FIG_TARGETS, True),
    "scene streets --out": (["scene", "streets", "sionna:simple_street_canyon", "--out", "{out}"], FIG_TARGETS, False),
    "scene streets --data": (["scene", "streets", "sionna:simple_street_canyon", "--out", "{fresh}.png", "--data",
                              "{out}"], NPZ_TARGETS, False),
    "paths --plot": (["paths", "{cache}", "--plot", "{out}"], FIG_TARGETS, True),
    "export": (["export", "{cache}", "--cfr", "--subcarriers", "8", "--out", "{out}"], NPZ_TARGETS, True),
}


@pytest.mark.parametrize("command", list(COMMANDS))
def test_every_writing_command_leaves_a_users_files_alone(tmp_path, capsys, cache, command):
    """Each writing command against a user's folder, file and symbolic links, with and without --force:
    exit 2 with one line, and the user's tree (every file's sha256, every link) exactly as before."""
    argv, targets, has_force = COMMANDS[command]
    area = user_area(tmp_path / "user")
    before = tree(tmp_path)
    for target in targets:
        for force in ([], ["--force"]) if has_force else ([],):
            args = [a.replace("{out}", str(area[target])).replace("{cache}", str(cache))
                     .replace("{fresh}", str(tmp_path / "fresh")) for a in argv] + force
            capsys.readouterr()
            rc = main(args)
            err = capsys.readouterr().err.strip()
            assert rc == 2, (args, rc, err)
            assert len(err.splitlines()) == 1 and err.startswith("error: "), (args, err)
            assert tree(tmp_path) == before, (args, err)
