"""CLI commands of this subpackage: ``mmslam trace``, ``mmslam paths`` and ``mmslam export``."""
from __future__ import annotations

import contextlib
from pathlib import Path
from typing import Optional

import numpy as np
import typer

from mmslam.errors import ConfigError, deferred_sigint

MAX_SUBCARRIERS = 1 << 20
MAX_TIME_STEPS = 10_000
MAX_EXPORT_BYTES = 8 << 30
"""Largest ``mmslam export`` response (bytes): a typo in --subcarriers must not exhaust memory."""
from mmslam.limits import MAX_CHUNK_STEPS, MAX_SAMPLES, MAX_SEED, MAX_STEPS, MAX_WORKERS, check_int, span

from mmslam.raytrace.schema import TYPE_LABELS as _TYPE_LABELS
_TYPE_COLORS = ("tab:blue", "tab:orange", "tab:green", "tab:red", "tab:gray")


def parse_steps(text: str | None, n_steps: int) -> np.ndarray | None:
    """``--steps`` of ``mmslam export``: ``"a:b"`` (b exclusive; either end may be left out), ``"a,b,c"``
    or a mix (``"0:5,9"``); None: every step. Raises a one-line ConfigError naming the bad part."""
    if text is None:
        return None
    out: list[int] = []
    for part in (p.strip() for p in str(text).split(",")):
        try:
            if ":" in part:
                lo, hi = (x.strip() for x in part.split(":", 1))
                a, b = int(lo) if lo else 0, int(hi) if hi else n_steps
                if not 0 <= a < b <= n_steps:
                    raise ValueError
                out.extend(range(a, b))
            else:
                k = int(part)
                if not 0 <= k < n_steps:
                    raise ValueError
                out.append(k)
        except ValueError:
            raise ConfigError(f"--steps {text}: '{part}' is not a step or a:b range within the cache's "
                              f"0..{n_steps - 1} (e.g. --steps 0:10 or --steps 3,7)") from None
    return np.array(sorted(set(out)), np.int64)


def parse_rx(text: str | None, names: list[str]) -> list[int] | None:
    """``--rx`` of ``mmslam export``: receiver names or indices, comma separated; None: every receiver."""
    if text is None:
        return None
    out = []
    for part in (p.strip() for p in str(text).split(",")):
        if part in names:
            out.append(names.index(part))
        elif part.isdigit() and int(part) < len(names):
            out.append(int(part))
        else:
            raise ConfigError(f"--rx {text}: no receiver '{part}'; expected names or indices of "
                              f"{', '.join(f'{i} {n}' for i, n in enumerate(names))}")
    return sorted(set(out))


def path_counts(paths: dict[str, np.ndarray], steps: int, n_rx: int) -> np.ndarray:
    """Number of path rows per (step, rx, type) as an ``(steps, n_rx, 5)`` int array."""
    key = (paths["step"].astype(np.int64) * n_rx + paths["rx"]) * len(_TYPE_LABELS) + paths["type"]
    return np.bincount(key, minlength=steps * n_rx * len(_TYPE_LABELS)).reshape(steps, n_rx, -1)


def plot_toa(cache, out: Path) -> None:
    """Figure of TOA (m, no clock bias) vs step, one colour per landmark type, one marker per receiver.

    The format follows ``out``'s suffix (png, pdf, svg)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from mmslam.outputs import save_figure

    p = cache.paths
    markers = "o^sDvP*X"
    fig, ax = plt.subplots(figsize=(8, 5))
    for r, name in enumerate(cache.vehicle_names):
        for t, (lab, col) in enumerate(zip(_TYPE_LABELS, _TYPE_COLORS)):
            sel = (p["rx"] == r) & (p["type"] == t)
            if sel.any():
                ax.scatter(p["step"][sel], p["toa_m"][sel], s=14, c=col, marker=markers[r % len(markers)],
                           label=f"{lab} (rx {name})", alpha=0.8)
    ax.set_xlabel(f"step (dt = {cache.scenario.dt:g} s)")
    ax.set_ylabel("TOA (m, delay x c, no clock bias)")
    ax.set_title(f"{cache.manifest['scenario']} - {cache.manifest['source']} paths")
    ax.grid(True, alpha=0.3)
    ax.legend(fontsize=8, ncol=2)
    try:
        save_figure(fig, out, dpi=120, bbox_inches="tight")
    finally:
        plt.close(fig)


def register(app: typer.Typer, scene: typer.Typer | None = None) -> None:
    """Add this subpackage's commands to ``app`` (and ``coverage`` to the ``scene`` group, if given)."""
    if scene is not None:
        _register_coverage(scene)

    @app.command("trace")
    def trace_cmd(
        scenario: str = typer.Argument(..., help="Preset name (paper, street) or a scenario .toml file."),
        source: str = typer.Option("sionna", "--source", help="Path source: sionna or analytic."),
        out: Path = typer.Option(Path("out/cache"), "--out", help="Cache root directory (the cache goes to "
                                 "OUT/<scenario>-<source>-<hash>); an existing one must be empty or hold caches."),
        steps: Optional[int] = typer.Option(None, "--steps", help="Steps to trace (default: the scenario's)." + span(1, MAX_STEPS)),
        max_depth: int = typer.Option(1, "--max-depth", help="Sionna max interactions per path." + span(1, 3)),
        samples: int = typer.Option(1_000_000, "--samples", help="Sionna rays per source." + span(1, MAX_SAMPLES)),
        seed: int = typer.Option(0, "--seed", help="Sionna ray-sampling seed." + span(0, MAX_SEED)),
        chunk_steps: int = typer.Option(5, "--chunk-steps", help="Steps per Parquet chunk." + span(1, MAX_CHUNK_STEPS)),
        force: bool = typer.Option(False, "--force/--no-force", help="Delete the existing cache of this "
                                   "configuration (one mmslam wrote) and trace anew. A folder or file mmslam did "
                                   "not write is never touched."),
        quiet: bool = typer.Option(False, "--quiet/--no-quiet", help="No progress bar."),
        executor: str = typer.Option("local", "--executor", help="local, or dask: chunks of steps traced on a "
                                     "Dask cluster (a LocalCluster of --workers processes, or --scheduler)."),
        workers: Optional[int] = typer.Option(None, "--workers", help="Dask LocalCluster workers (default: CPU "
                                              "cores, at most one per chunk)." + span(1, MAX_WORKERS)),
        scheduler: Optional[str] = typer.Option(None, "--scheduler", help="Address of a running Dask scheduler."),
    ) -> None:
        """Trace a scenario into a resumable path cache; prints the cache directory."""
        from mmslam.executor import check_executor

        check_executor(executor, scheduler, workers)  # the address is checked here, before any work
        from mmslam.raytrace.trace import (SOURCES, DaskExecutor, check_cache_root, check_scene, make_source,
                                           trace_scenario)
        from mmslam.scenes.scenario import resolve_scenario

        if source not in SOURCES:
            raise ConfigError(f"--source '{source}': unknown; expected one of {', '.join(SOURCES)}")
        if not 1 <= max_depth <= 3:
            raise ConfigError(f"--max-depth {max_depth}: expected 1, 2 or 3")
        check_int("--steps", steps, 1, MAX_STEPS, "a number of steps")
        check_int("--samples", samples, 1, MAX_SAMPLES, "rays per source")
        check_int("--seed", seed, 0, MAX_SEED, "a seed")
        check_int("--chunk-steps", chunk_steps, 1, MAX_CHUNK_STEPS)
        if executor == "local" and (workers is not None or scheduler):
            raise ConfigError("--workers / --scheduler are only used with --executor dask")
        check_cache_root(out, force)  # before the scene is built
        scn = resolve_scenario(scenario)
        check_scene(scn, steps)  # before the (slow) scene load of the source
        from mmslam.scenes.scenario import scenario_route_points
        from mmslam.scenes.trajectory import route_warnings, true_trajectories

        for line in route_warnings(scn, true_trajectories(scn, steps), scenario_route_points(scn)):
            typer.echo(f"warning: {line}", err=True)
        ex = None
        if executor == "dask":
            ex = DaskExecutor({"name": source, "max_depth": max_depth, "samples": samples, "seed": seed},
                              scheduler=scheduler, workers=workers)
        with ex if ex is not None else contextlib.nullcontext():  # a --scheduler is reached before any work
            with deferred_sigint():  # the Sionna scene load is C++: Ctrl-C is raised after it
                src = make_source(source, scn, max_depth=max_depth, samples=samples, seed=seed)
            d = trace_scenario(scn, src, out, steps=steps, chunk_steps=chunk_steps, force=force,
                               progress=not quiet, executor=ex, notice=lambda s: typer.echo(f"note: {s}", err=True))
        from mmslam.raytrace.cache import load_cache
        from mmslam.raytrace.trace import coverage_warnings

        c = load_cache(d)
        for line in coverage_warnings(c.paths, c.steps, c.vehicle_names):
            typer.echo(f"warning: {line}", err=True)
        typer.echo(str(d))

    @app.command("paths")
    def paths_cmd(
        cache_dir: Path = typer.Argument(..., help="A cache directory, or a root holding caches (several: "
                                         "they are listed; pick one with --source)."),
        source: Optional[str] = typer.Option(None, "--source", help="In a root with several caches: the one "
                                             "traced by this source (sionna or analytic)."),
        plot: Optional[Path] = typer.Option(None, "--plot", help="Write a figure of TOA vs step to this file; "
                                            "the format follows the suffix (.png, .pdf, .svg)."),
        force: bool = typer.Option(False, "--force/--no-force", help="Accepted for old scripts; changes nothing: "
                                   "a figure mmslam wrote is replaced anyway, any other file never."),
    ) -> None:
        """Print the number of paths per type, step and receiver of a path cache."""
        from rich.console import Console
        from rich.table import Table

        from mmslam.outputs import check_figure_target
        from mmslam.raytrace.cache import MANIFEST, find_cache_dir, list_caches, load_cache
        from mmslam.raytrace.trace import SOURCES

        if source is not None and source not in SOURCES:
            raise ConfigError(f"--source '{source}': unknown; expected one of {', '.join(SOURCES)}")
        if plot is not None:
            check_figure_target(plot, force, option="--plot")  # before the cache is read
        many = list_caches(cache_dir) if not (Path(cache_dir) / MANIFEST).is_file() else []
        if source is None and len(many) > 1:
            if plot is not None:
                raise ConfigError(f"{cache_dir}: holds {len(many)} caches ({', '.join(d.name for d in many)}); "
                                  "give one of them, or --source sionna|analytic")
            for d in many:
                c = load_cache(d)
                typer.echo(f"{d}: source {c.manifest['source']}, {c.steps} steps, {len(c.paths['rx'])} paths")
            typer.echo(f"{len(many)} caches; give one of them, or --source sionna|analytic, for the table")
            return
        c = load_cache(find_cache_dir(cache_dir, source))
        names = c.vehicle_names
        counts = path_counts(c.paths, c.steps, len(names))
        n_rays = sum(int(ch["rows"]["rays"]) for ch in c.manifest["chunks"])
        tbl = Table(title=f"{c.path.name}: {c.steps} steps, {len(c.paths['rx'])} paths from {n_rays} rays "
                          f"(source {c.manifest['source']})")
        tbl.add_column("step", justify="right")
        tbl.add_column("rx")
        for lab in _TYPE_LABELS:
            tbl.add_column(lab, justify="right")
        tbl.add_column("total", justify="right")
        for k in range(c.steps):
            for r, name in enumerate(names):
                row = counts[k, r]
                tbl.add_row(str(k), name, *map(str, row.tolist()), str(int(row.sum())))
        tot = counts.sum(axis=(0, 1))
        tbl.add_row("all", "all", *map(str, tot.tolist()), str(int(tot.sum())), style="bold")
        Console(width=100).print(tbl)
        if plot is not None:
            plot_toa(c, plot)
            typer.echo(f"wrote {plot}")

    @app.command("export")
    def export_cmd(
        cache_dir: Path = typer.Argument(..., help="A cache directory (or a root holding one cache)."),
        cir: bool = typer.Option(False, "--cir", help="Channel impulse response taps (sinc pulse at --bandwidth)."),
        cfr: bool = typer.Option(False, "--cfr", help="Channel frequency response at the subcarriers."),
        bandwidth: float = typer.Option(400e6, "--bandwidth", help="Bandwidth W in Hz."),
        subcarriers: int = typer.Option(1024, "--subcarriers",
                                        help="Subcarriers (CFR; spacing W / N) or taps l_min..N-1 (CIR)."
                                        + span(1, MAX_SUBCARRIERS)),
        l_min: int = typer.Option(0, "--l-min", help="First CIR tap index (negative: sinc leakage before 0)."),
        time_steps: int = typer.Option(1, "--time-steps", help="Doppler evolution: samples at t = n / W per step."
                                       + span(1, MAX_TIME_STEPS)),
        no_normalize_delays: bool = typer.Option(False, "--no-normalize-delays",
                                                 help="Keep absolute delays (default: first ray of a link at 0)."),
        steps: Optional[str] = typer.Option(None, "--steps", help="Steps to export: a:b (b exclusive), a,b,c or a "
                                            "mix, e.g. 0:10 (default: every cached step)."),
        rx: Optional[str] = typer.Option(None, "--rx", help="Receivers to export: vehicle names or indices, comma "
                                         "separated (default: every vehicle)."),
        sampling_frequency: Optional[float] = typer.Option(None, "--sampling-frequency", help="Sampling frequency "
                                                           "fs in Hz of the --time-steps samples t = n / fs within a "
                                                           "step (default: --bandwidth)."),
        with_arrays: bool = typer.Option(False, "--arrays", help="With the scenario's BS and vehicle arrays "
                                         "(sensor.tx_array / rx_array elements per axis): antenna axes "
                                         "(steps, rx, rx_ant, tx_ant, time, K)."),
        out: Path = typer.Option(..., "--out", help="Output .npz file (h, axis, times_s, steps, rx_names, meta); "
                                 "an existing one must be an export mmslam wrote."),
        force: bool = typer.Option(False, "--force/--no-force", help="Accepted for old scripts; changes nothing: "
                                   "an .npz mmslam exported is replaced anyway, any other file never."),
    ) -> None:
        """Export the CIR or CFR of every step and receiver of a cache (from its rays table) to an .npz file."""
        from mmslam.outputs import check_npz_target
        from mmslam.raytrace.cache import atomic_write_bytes, load_cache
        from mmslam.raytrace.channel import NPZ_KIND, cache_channel_response

        if cir == cfr:
            raise ConfigError("mmslam export: give exactly one of --cir or --cfr")
        if out.suffix != ".npz":
            raise ConfigError(f"--out {out}: expected a file name ending in .npz")
        check_int("--subcarriers", subcarriers, 1, MAX_SUBCARRIERS)
        check_int("--time-steps", time_steps, 1, MAX_TIME_STEPS)
        if sampling_frequency is not None and not (0 < sampling_frequency < float("inf")):
            raise ConfigError(f"--sampling-frequency {sampling_frequency:g}: expected a frequency > 0 in Hz")
        if cir and l_min > subcarriers - 1:  # the CIR taps are l_min .. subcarriers - 1 (there is no --l-max)
            raise ConfigError(f"--l-min {l_min}: expected at most --subcarriers - 1 = {subcarriers - 1} (the CIR "
                              "taps are l_min .. subcarriers - 1); lower --l-min or raise --subcarriers")
        if cir and subcarriers - min(l_min, 0) > MAX_SUBCARRIERS:  # the taps l_min .. subcarriers - 1
            raise ConfigError(f"--l-min {l_min}: the CIR would have {subcarriers - min(l_min, 0)} taps (l_min .. "
                              f"subcarriers - 1), at most {MAX_SUBCARRIERS}; raise --l-min or lower --subcarriers")
        c = load_cache(cache_dir)
        step_sel = parse_steps(steps, c.steps)
        rx_sel = parse_rx(rx, list(c.vehicle_names))
        check_npz_target(out, NPZ_KIND, force, protect=(c.path,))
        n_steps = c.steps if step_sel is None else step_sel.size
        n_rx = len(c.vehicle_names) if rx_sel is None else len(rx_sel)
        ants = int(c.scenario.sensor.tx_array) ** 2 * int(c.scenario.sensor.rx_array) ** 2 if with_arrays else 1
        size = n_steps * n_rx * ants * time_steps * (subcarriers - min(l_min, 0)) * 8  # complex64
        if size > MAX_EXPORT_BYTES:
            raise ConfigError(f"mmslam export: the response would take {size / 2**30:.1f} GiB (steps x receivers x "
                              f"--time-steps x {'taps' if cir else '--subcarriers'}"
                              f"{' x antennas' if with_arrays else ''}); at most "
                              f"{MAX_EXPORT_BYTES / 2**30:.0f} GiB: lower --subcarriers or --time-steps"
                              f"{', raise --l-min' if cir and l_min < 0 else ''}, or export fewer --steps / --rx")
        resp = cache_channel_response(c, kind="cir" if cir else "cfr", bandwidth_hz=bandwidth,
                                      n_subcarriers=subcarriers, steps=step_sel, l_min=l_min,
                                      num_time_steps=time_steps, normalize_delays=not no_normalize_delays,
                                      sampling_frequency_hz=sampling_frequency, arrays=with_arrays)
        if rx_sel is not None:  # h is (steps, rx, ...)
            import dataclasses

            resp = dataclasses.replace(resp, h=resp.h[:, rx_sel], rx_names=[resp.rx_names[i] for i in rx_sel])
        atomic_write_bytes(out, resp.to_npz_bytes())
        typer.echo(f"wrote {out}: {resp.kind} h{tuple(resp.h.shape)} (steps, rx, {'rx_ant, tx_ant, ' if with_arrays else ''}time, "
                   f"{'frequency' if cfr else 'tap'})")


def _register_coverage(scene: typer.Typer) -> None:
    """``mmslam scene coverage``: the Sionna radio map lives in this layer (raytrace), above scenes."""

    @scene.command("coverage")
    def coverage_cmd(
        scenario: str = typer.Argument(..., help="Preset name or a scenario .toml file."),
        out: Path = typer.Option(Path("coverage.png"), "--out", help="Figure of the radio map; the format "
                                 "follows the suffix (.png, .pdf, .svg)."),
        height: float = typer.Option(1.5, "--height", help="Plane height above the street (m)."),
        res: float = typer.Option(2.0, "--res", help="Cell size (m)."),
        margin: float = typer.Option(40.0, "--margin", help="Map extent beyond the BS and the routes (m)."),
        samples: int = typer.Option(1_000_000, "--samples", help="Rays shot from the BS."),
        max_depth: int = typer.Option(1, "--max-depth", help="Interactions per path (as mmslam trace). [1..3]"),
        seed: int = typer.Option(0, "--seed", help="Sionna's sampling seed."),
        force: bool = typer.Option(False, "--force/--no-force", help="Accepted for old scripts; changes nothing: "
                                   "a figure mmslam wrote is replaced anyway, any other file never."),
    ) -> None:
        """Sionna's radio map (RadioMapSolver) of the BS at street level over the plan, with the routes.

        Shows where the BS reaches before anything is traced; prints, per vehicle, the path gain
        along its route and the steps where no path reaches it.
        """
        import numpy as np

        from mmslam.errors import ConfigError
        from mmslam.limits import MAX_SAMPLES, MAX_SEED, check_int
        from mmslam.outputs import check_figure_target
        from mmslam.raytrace.coverage import coverage_map, plot_coverage, route_gain_db
        from mmslam.scenes.scenario import resolve_scenario
        from mmslam.scenes.trajectory import vehicle_trajectories

        check_figure_target(out, force)
        check_int("--samples", samples, 1, MAX_SAMPLES, "rays")
        check_int("--seed", seed, 0, MAX_SEED, "a seed")
        if not 1 <= max_depth <= 3:
            raise ConfigError(f"--max-depth {max_depth}: expected 1, 2 or 3")
        if not 0.0 <= margin <= 1000.0:
            raise ConfigError(f"--margin {margin}: expected 0 .. 1000 m")
        scn = resolve_scenario(scenario)
        states = vehicle_trajectories(scn)
        cm = coverage_map(scn, states, height=height, res=res, margin=margin, samples=samples,
                          max_depth=max_depth, seed=seed)
        g = route_gain_db(cm, states)
        for i, v in enumerate(scn.vehicles):
            gi = g[:, i]
            ok = gi[np.isfinite(gi)]
            med = f"median {np.median(ok):.1f} dB, min {ok.min():.1f} dB" if ok.size else "no path anywhere"
            typer.echo(f"{v.name}: path gain along the route {med}; no path in {int(np.isneginf(gi).sum())} "
                       f"of {len(gi)} steps")
        typer.echo(f"wrote {plot_coverage(cm, scn, states, out)}")
