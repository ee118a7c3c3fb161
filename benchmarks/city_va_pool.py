"""Run ``benchmarks/city_va.py`` over many scenes and seeds in parallel processes, resumable, and merge per scene.

    python benchmarks/city_va_pool.py CACHE [CACHE ...] --seeds 15740-15839 --out DIR [--chunk 10] [--jobs N]
        -- [city_va options: --odometry --ignore-va --compare ...]

Each (scene, chunk of ``--chunk`` consecutive seeds) is one ``city_va.py`` process writing
``DIR/chunks/<scene>.<first>-<last>.json``; a chunk whose file exists is not run again (a stopped run resumes). The
chunks run in the order of the caches given, then of the seeds, ``--jobs`` at a time; a chunk whose file appears
while the pool runs (copied from another machine running the same seeds) is skipped. Once every chunk of a scene is
there, ``DIR/<scene>.json`` holds its rows in seed order, in ``city_va.py --save``'s format (the summary: the
seed-independent entries, ``floor2`` and the path statistics; the paired statistics are for the reader of the rows).
One run per seed is independent of the others (each seed's draws come from its own generator), so the rows do not
depend on the chunking. Before the pool, one short run (one seed, 12 steps) fills numba's cache, so the processes load
the compiled kernels instead of compiling them each. Prints one line per chunk done; exit status 1 if a chunk failed
(its log says why; the same command retries it). Two caches of one scene (traced and analytic) need two --out folders.
"""
from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))
from city_va import is_city_va_save, seeds_of  # noqa: E402

SEED_INDEPENDENT = ("floor2", "va_paths_per_step", "nlos_with_va")


def scene_of(cache: str) -> str:
    """``munich3-sionna-38b5...`` -> ``munich3`` (the cache folder's name less its source and hash)."""
    name = Path(cache).resolve().name
    return name.rsplit("-", 2)[0] if name.count("-") >= 2 else name


def chunks(seeds: list[int], size: int) -> list[list[int]]:
    return [seeds[i:i + size] for i in range(0, len(seeds), size)]


def merge(scene: str, files: list[Path], out: Path) -> None:
    """``out``: the chunks' rows in seed order and their seed-independent summary entries."""
    parts = [json.loads(f.read_text())[0] for f in files]
    rows = sorted((r for p in parts for r in p["rows"]), key=lambda r: r["seed"])
    summary = {k: v for k, v in parts[0]["summary"].items() if k in SEED_INDEPENDENT}
    doc = [{"scene": parts[0]["scene"], "cache": parts[0]["cache"], "rows": rows, "summary": summary}]
    tmp = out.with_suffix(".json.tmp")
    tmp.write_text(json.dumps(doc, indent=1))
    os.replace(tmp, out)


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    extra: list[str] = []
    if "--" in argv:
        i = argv.index("--")
        argv, extra = argv[:i], argv[i + 1:]
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("cache", nargs="+")
    ap.add_argument("--seeds", type=seeds_of, required=True)
    ap.add_argument("--out", required=True, help="folder of the chunks and the merged files (made if missing)")
    ap.add_argument("--chunk", type=int, default=10, help="seeds per process (default 10)")
    ap.add_argument("--jobs", type=int, default=os.cpu_count() or 1, help="processes at a time (default: the cores)")
    a = ap.parse_args(argv)
    if a.chunk < 1 or a.jobs < 1:
        ap.error("--chunk and --jobs must be at least 1")
    for c in a.cache:
        if not Path(c).is_dir():
            ap.error(f"{c}: no such cache folder (trace it first: mmslam trace SCENARIO --out DIR)")
    names = [scene_of(c) for c in a.cache]
    twice = sorted({n for n in names if names.count(n) > 1})
    if twice:  # their chunk and merged files would share names
        ap.error(f"two caches of scene {twice[0]!r} (e.g. traced and analytic): run them with separate --out folders")
    out = Path(a.out)
    for n in names:  # the merged files replace only what an earlier pool (or city_va --save) wrote
        f = out / f"{n}.json"
        if f.exists() and not is_city_va_save(f):
            ap.error(f"{f} exists and is not a city_va result: choose another --out (nothing was run)")
    (out / "chunks").mkdir(parents=True, exist_ok=True)
    py = sys.executable
    script = str(HERE / "city_va.py")
    todo = [(c, s) for c in a.cache for s in chunks(a.seeds, a.chunk)]

    def target(cache: str, ss: list[int]) -> Path:
        return out / "chunks" / f"{scene_of(cache)}.{ss[0]}-{ss[-1]}.json"

    pending = [(c, s) for c, s in todo if not target(c, s).exists()]
    print(f"{len(todo)} chunks, {len(todo) - len(pending)} done before, {a.jobs} at a time", flush=True)
    if pending:  # fill numba's cache once
        warm = subprocess.run([py, script, pending[0][0], "--seeds", str(pending[0][1][0]), "--steps", "12"] + extra,
                              stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
        if warm.returncode:  # e.g. a city_va option mistyped after --: its own one-line error
            last = (warm.stderr.strip().splitlines() or ["(no message)"])[-1]
            print(f"city_va_pool: the first run failed, nothing else was run: {last}", file=sys.stderr)
            return 2
    t0 = time.perf_counter()

    def run(job: tuple[str, list[int]]) -> str:
        cache, ss = job
        dest = target(cache, ss)
        if dest.exists():  # another machine's pool finished it meanwhile (its chunk copied here)
            return f"{dest.name}: there already"
        seeds = ",".join(str(x) for x in ss)
        log = dest.with_suffix(".log")
        with open(log, "w") as fh:
            rc = subprocess.run([py, script, cache, "--seeds", seeds, "--save", str(dest)] + extra,
                                stdout=fh, stderr=subprocess.STDOUT).returncode
        return f"{dest.name}: rc {rc}, {time.perf_counter() - t0:.0f} s"

    failed = 0
    with ThreadPoolExecutor(a.jobs) as ex:
        for line in ex.map(run, pending):
            failed += " rc 0," not in line and not line.endswith("there already")
            print(line, flush=True)
    for cache in dict.fromkeys(a.cache):
        files = [target(cache, s) for s in chunks(a.seeds, a.chunk)]
        if all(f.exists() for f in files):
            merge(scene_of(cache), files, out / f"{scene_of(cache)}.json")
    if failed:
        print(f"{failed} chunk(s) failed: see their .log files under {out / 'chunks'}; re-run the same command to "
              "retry them", file=sys.stderr)
    return 1 if failed else 0


if __name__ == "__main__":
    raise SystemExit(main())
