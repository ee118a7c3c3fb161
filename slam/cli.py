"""CLI commands of the SLAM subpackage: ``mmslam slam`` (registered on the top-level app)."""
from __future__ import annotations

from pathlib import Path
from typing import Optional

import typer

from mmslam.errors import Interrupted, MmslamError, was_interrupted
from mmslam.limits import MAX_PARTICLES, MAX_SEED, MAX_STEPS, check_int, span


def summarize(res) -> list[tuple[str, str, float, float, float, float]]:
    """Mean GOSPA per (map, type) over the steps from the first fusion on, with what it is measured against:
    ``[(map, type, mean GOSPA (m), mean GOSPA of an empty map (m), mean truths, mean estimates)]``.

    The first fusion step is ``min(fusion.start)`` recorded in ``meta['fusion_start']`` (0 if
    absent). The empty map's GOSPA at a step is ``(c^p / alpha * n_true)^(1/p)`` (every truth missed), with the run's
    ``meta['gospa']`` (``[evaluation]``; NaN for a result written before it was recorded). Rows are in the order maps
    first appear in the metrics table, types VA, SP, VS.
    """
    import numpy as np

    from mmslam.slam.eval.evaluation import evaluated_types

    type_names = [s.name for s in evaluated_types()]
    m = res.metrics
    start = int(res.meta.get("fusion_start", 0))
    sel = np.asarray(m["step"]) >= start
    g = res.meta.get("gospa")
    n_true, n_est = np.asarray(m["n_true"], float), np.asarray(m["n_est"], float)
    empty = ((g["c"] ** g["p"] / g["alpha"] * n_true) ** (1.0 / g["p"]) if g else np.full(n_true.shape, np.nan))
    maps = list(dict.fromkeys(np.asarray(m["map"])[sel].tolist()))
    out = []
    for mp in maps:
        for t in type_names:
            s = sel & (np.asarray(m["map"]) == mp) & (np.asarray(m["type"]) == t)
            if s.any():
                out.append((mp, t, float(np.mean(np.asarray(m["gospa"])[s])), float(np.mean(empty[s])),
                            float(np.mean(n_true[s])), float(np.mean(n_est[s]))))
    return out


def variant_help() -> str:
    """Every registered variant and what it runs (:meth:`VariantSpec.describe`), for ``--help``."""
    from mmslam.slam.specs.variants import get_variant, variant_names

    return " ".join(f"{v}: {get_variant(v).describe()}." for v in variant_names())


def register(app: typer.Typer) -> None:
    """Add ``mmslam slam`` to ``app``."""
    from mmslam.slam.specs.variants import DEFAULT_VARIANT

    @app.command("slam")
    def slam_cmd(
        cache: Path = typer.Argument(..., help="Path cache directory (from `mmslam trace`)."),
        variant: str = typer.Option(DEFAULT_VARIANT, help="Filter variant. " + variant_help()),
        particles: Optional[int] = typer.Option(None, help="Particles per vehicle (default: the scenario's "
                                                "filter.particles)." + span(1, MAX_PARTICLES)),
        seed: int = typer.Option(0, help="Monte Carlo seed (measurement noise, clutter, prior, filter)." + span(0, MAX_SEED)),
        out: Path = typer.Option(..., "--out", help="Result directory to write (atomically). An existing "
                                 "directory is replaced only if it is empty or a previous result holding only "
                                 "a result's files."),
        force: bool = typer.Option(False, "--force/--no-force", help="Accepted for old scripts; changes nothing: "
                                   "--out is replaced only if it is a previous result, and a folder or file mmslam "
                                   "did not write is never touched."),
        steps: Optional[int] = typer.Option(None, help="Run only the first N steps of the cache." + span(1, MAX_STEPS)),
        sets: list[str] = typer.Option([], "--set", help="section.key=value override of a filter, fusion, sensor "
                                       "or evaluation parameter (repeatable), e.g. --set fusion.vs_reduction=gate; "
                                       "see docs/scenario.md. Parameters of the trace are refused."),
        ignore_types: str = typer.Option("", "--ignore-types", help="Path types (comma-separated names, e.g. VA) "
                                         "left out of the measurements: the filter never sees them (e.g. VA: "
                                         "localisation without wall bounces, the reference for what the VA map "
                                         "adds)."),
        animate: Optional[Path] = typer.Option(None, "--animate", help="Also draw the run step by step (vehicles, "
                                               "the fused map's estimates vs truth, the traced paths) into this "
                                               ".gif (or .mp4, needs ffmpeg) file."),
    ) -> None:
        """Run cooperative MM-PHD-SLAM on a path cache and write the Result (vehicles, metrics, landmarks)."""
        import numpy as np
        from rich.console import Console
        from rich.table import Table

        from mmslam.slam.filter import run_slam
        from mmslam.slam.specs.variants import variant_names

        if variant not in variant_names():
            raise MmslamError(f"--variant {variant!r}: expected one of {', '.join(variant_names())}")
        check_int("--particles", particles, 1, MAX_PARTICLES, "a number of particles")
        check_int("--steps", steps, 1, MAX_STEPS, "a number of steps")
        check_int("--seed", seed, 0, MAX_SEED, "a seed")
        include = None
        if ignore_types.strip():
            from mmslam.slam.specs.landmarks import landmark_type, landmark_types

            try:
                drop = {landmark_type(x.strip()).code for x in ignore_types.split(",") if x.strip()}
            except MmslamError as e:
                raise MmslamError(f"--ignore-types {ignore_types!r}: {e}") from None
            include = tuple(t.code for t in landmark_types() if t.code not in drop)
        from mmslam.outputs import check_target, locked
        from mmslam.slam.filter.result import RESULT_FILES, RESULT_KIND

        if animate is not None:
            from mmslam.slam.eval.viewer import check_animation_target

            check_animation_target(animate, force)  # before the computation
        with locked(out, "slam"):
            check_target(out, RESULT_KIND, force, protect=(cache,), own_names=RESULT_FILES,
                         writes=RESULT_FILES)  # before the computation
            try:
                res = run_slam(cache, variant=variant, particles=particles, seed=seed, steps=steps,
                               overrides=tuple(sets), include_types=include, compile_notice=lambda m: Console().print(
                                   m, highlight=False, soft_wrap=True))  # stdout: stderr is for errors
            except BaseException as e:
                if not was_interrupted(e):
                    raise
                raise Interrupted(f"nothing was written to {out} (a single run does not resume); re-run the same "
                                  "command") from None
            path = res.save(out, force=force)
        con = Console()
        tab = Table(title=f"mmslam slam: {variant}, P={res.meta['particles']}, seed={seed}, "
                          f"{res.meta['steps']} steps (GOSPA means from step {res.meta.get('fusion_start', 0)})")
        tab.add_column("map")
        tab.add_column("type")
        tab.add_column("mean GOSPA \\[m]", justify="right")
        tab.add_column("empty map \\[m]", justify="right")
        tab.add_column("ratio", justify="right")
        tab.add_column("truths", justify="right")
        tab.add_column("estimates", justify="right")
        rows = summarize(res)
        for mp, t, g, e, nt, ne in rows:
            tab.add_row(mp, t, f"{g:.2f}", f"{e:.2f}", f"{g / e:.2f}" if e > 0 else "-", f"{nt:.1f}", f"{ne:.1f}")
        con.print(tab)
        if rows:
            con.print("empty map: the GOSPA of a map with no estimate (every truth missed); ratio: mean GOSPA over it "
                      "(below 1: the map is better than none); truths, estimates: per step", highlight=False,
                      soft_wrap=True)
        if not rows:  # e.g. --steps 4 on `paper`, whose first upload is at step 5: localisation only
            con.print(f"note: the run has {res.meta['steps']} steps and the first map fusion is at step "
                      f"{res.meta.get('fusion_start', 0)}: no map was fused or scored; run more steps, or set an "
                      "earlier fusion.start (--set fusion.start=[...])", highlight=False, soft_wrap=True)
        v = res.vehicles
        names = res.meta.get("vehicle_names", [])
        for i in np.unique(v["vehicle"]):
            s = v["vehicle"] == i
            rmse = float(np.sqrt(np.mean(np.asarray(v["pos_err"])[s] ** 2)))
            name = names[int(i)] if int(i) < len(names) else str(int(i))
            con.print(f"position RMSE {name}: {rmse:.3f} m")
        con.print(f"wall time: {res.meta['wall_time_s']:.1f} s; written to {path}")
        if animate is not None:
            from mmslam.slam.eval.viewer import animate as draw_animation
            from mmslam.slam.eval.viewer import viewer_data
            from mmslam.raytrace.cache import load_cache

            c = load_cache(cache)
            draw_animation(viewer_data(res, c.scenario, c.paths), animate)
            con.print(f"animation: {animate}")
