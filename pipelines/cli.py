"""CLI commands of this subpackage: ``mmslam demo``, ``mmslam ablate`` and ``mmslam report``.

Thin wrappers over :mod:`mmslam.pipelines.demo`, :mod:`mmslam.pipelines.ablate` and
:mod:`mmslam.pipelines.report`; argument checks happen before any work starts.
"""
from __future__ import annotations

from pathlib import Path
from typing import Optional

import typer

from mmslam.errors import ConfigError
from mmslam.limits import (MAX_MC, MAX_PARTICLES, MAX_SAMPLES, MAX_SEED, MAX_STEPS, MAX_WORKERS, check_int, span)
from mmslam.slam.cli import variant_help
from mmslam.slam.specs.variants import BUILTIN_VARIANTS

def _check_source(source: str) -> None:
    from mmslam.raytrace.trace import SOURCES

    if source not in SOURCES:
        raise ConfigError(f"--source '{source}': unknown; expected one of {', '.join(SOURCES)}")


def _scenario_file(scenario: str) -> Path:
    """The TOML file of a preset name or a scenario path (per-run truth resolves it again per run)."""
    from mmslam.scenes.scenario import preset_path

    return Path(scenario) if scenario.endswith(".toml") or Path(scenario).is_file() else preset_path(scenario)


def _print_summary(summary, title: str, extra: list[str]) -> None:
    from rich.console import Console

    from mmslam.pipelines.report import summary_console_table

    con = Console()
    if not con.is_terminal:  # piped or logged: rich would wrap the table at 80 columns
        con = Console(width=160)
    con.print(summary_console_table(summary, title, width=con.width))
    for line in extra:
        con.print(line, highlight=False, soft_wrap=True, markup=False)


def register(app: typer.Typer) -> None:
    """Add this subpackage's commands to ``app``."""

    @app.command("demo")
    def demo_cmd(
        source: str = typer.Option("sionna", "--source", help="Path source: sionna (ray traced) or analytic."),
        mc: int = typer.Option(10, "--mc", help="Monte Carlo runs per variant (seeds 0..mc-1)." + span(1, MAX_MC)),
        particles: Optional[int] = typer.Option(None, "--particles", help="Particles per vehicle filter (default: "
                                                "the scenario's filter.particles)." + span(1, MAX_PARTICLES)),
        out: Path = typer.Option(Path("out/demo"), "--out", help="Output directory (cache, jobs, report); an "
                                 "existing one must be empty or a previous demo / ablation."),
        workers: Optional[int] = typer.Option(None, "--workers", help="Worker processes (default: all cores)." + span(1, MAX_WORKERS)),
        force: bool = typer.Option(False, "--force/--no-force", help="Accepted for old scripts; changes nothing: "
                                   "a folder mmslam did not write is never written into."),
        quiet: bool = typer.Option(False, "--quiet/--no-quiet", help="No progress bars."),
    ) -> None:
        """The main job: paper preset, baseline / cm1 / proposed x MC runs, summary and HTML report."""
        from mmslam.pipelines.ablate import check_run_args
        from mmslam.pipelines.demo import run_demo

        _check_source(source)
        check_run_args(mc, particles, None, "local", None, workers)
        res = run_demo(source=source, mc=mc, particles=particles, out=out, workers=workers, progress=not quiet,
                       force=force)
        run = res.ablation
        _print_summary(run.summary, f"paper ({source}), {mc} runs, P = {res.particles}", [
            f"jobs: {len(run.ran)} run, {len(run.skipped)} reused ({run.executor}); ablation wall time "
            f"{run.wall_time_s:.1f} s",
            f"report: {res.report}"])

    @app.command("ablate")
    def ablate_cmd(
        scenario: str = typer.Argument(..., help="Preset name (paper, street) or a scenario .toml file."),
        variants: str = typer.Option(",".join(BUILTIN_VARIANTS), "--variants",
                                     help="Comma-separated variants. " + variant_help()),
        mc: int = typer.Option(10, "--mc", help="Monte Carlo runs per variant (seeds seed0..seed0+mc-1)." + span(1, MAX_MC)),
        particles: Optional[int] = typer.Option(None, "--particles", help="Particles per vehicle filter (default: "
                                                "the scenario's filter.particles)." + span(1, MAX_PARTICLES)),
        source: str = typer.Option("sionna", "--source", help="Path source: sionna or analytic."),
        out: Path = typer.Option(..., "--out", help="Ablation directory (cache, jobs, summary); an existing one "
                                 "must be empty or a previous ablation. One writer at a time (lock file)."),
        steps: Optional[int] = typer.Option(None, "--steps", help="Time steps (default: the scenario's)." + span(1, MAX_STEPS)),
        cache_root: Optional[Path] = typer.Option(None, "--cache", help="Folder of caches to trace into or reuse "
                                                  "(e.g. the --out of mmslam trace; default: OUT/cache)."),
        executor: str = typer.Option("local", "--executor", help="local (process pool) or dask."),
        scheduler: Optional[str] = typer.Option(None, "--scheduler",
                                                help="Dask scheduler address, e.g. tcp://host:8786 "
                                                     "(default: start a local cluster)."),
        workers: Optional[int] = typer.Option(None, "--workers", help="Worker processes (default: all cores)." + span(1, MAX_WORKERS)),
        max_depth: int = typer.Option(1, "--max-depth", help="Sionna max interactions per path." + span(1, 3)),
        samples: int = typer.Option(1_000_000, "--samples", help="Sionna rays per source." + span(1, MAX_SAMPLES)),
        report: bool = typer.Option(False, "--report/--no-report", help="Also write figures and the HTML report."),
        force: bool = typer.Option(False, "--force/--no-force", help="Accepted for old scripts; changes nothing: "
                                   "a folder mmslam did not write is never written into."),
        quiet: bool = typer.Option(False, "--quiet/--no-quiet", help="No progress bars."),
        seed0: int = typer.Option(0, "--seed0", help="First seed: runs use seeds seed0 .. seed0+mc-1." + span(0, MAX_SEED)),
        sets: list[str] = typer.Option([], "--set", help="section.key=value parameter override for every "
                                       "run (repeatable), e.g. --set fusion.vs_reduction=gate; see docs/scenario.md."),
        grid: list[str] = typer.Option([], "--grid", help="section.key=v1,v2: run every variant once per value "
                                       "(repeatable: all combinations), e.g. --grid filter.vs_dither_scope=newborn,all."),
        truth: str = typer.Option("per-run", "--truth", help="per-run: with --source analytic, run s draws its own "
                                  "true trajectories (process noise, random SP heights) from seed s; fixed: every run "
                                  "uses the cache's truth (drawn once from the scenario seed). Sionna caches are "
                                  "always fixed (per-run truth would need a trace per run); summary.json's "
                                  "config.truth says which."),
    ) -> None:
        """Run the (variant x grid arm x seed) jobs; finished jobs are kept and skipped on re-runs."""
        from mmslam.outputs import locked
        from mmslam.pipelines.ablate import (check_grid_clash, check_overrides, check_run_args, default_command,
                                             parse_grid, parse_sets, parse_variants, particles_for, precheck_ablation,
                                             prepare_cache, run_ablation, start_ablation_dir)
        from mmslam.scenes.scenario import resolve_scenario

        vs = parse_variants(variants)
        _check_source(source)
        check_run_args(mc, particles, steps, executor, scheduler, workers, seed0)
        if not 1 <= max_depth <= 3:
            raise ConfigError(f"--max-depth {max_depth}: expected 1, 2 or 3")
        check_int("--samples", samples, 1, MAX_SAMPLES, "rays per source")
        sets_c, arms = parse_sets(sets), parse_grid(grid)  # syntax checked before the trace
        check_grid_clash(sets_c, arms)
        if truth not in ("per-run", "fixed"):
            raise ConfigError(f"--truth {truth!r}: expected per-run or fixed")
        scn = resolve_scenario(scenario)
        check_overrides(scn, sets_c, arms)  # values too: before the lock, the trace and any write
        particles = particles_for(scn, sets_c, particles)
        notes: list[str] = []
        if cache_root is None and (Path(out) / "ablation.json").is_file():  # resumed without the --cache it ran on
            from mmslam.pipelines.ablate.store import read_ablation

            rec = Path(str(read_ablation(out).get("cache_dir") or ""))
            if rec.name and rec.is_dir() and rec.parent.resolve() != (Path(out) / "cache").resolve():
                cache_root = rec.parent
                notes.append(f"cache: {rec} (this ablation's --cache, recorded in {Path(out) / 'ablation.json'})")
        if cache_root is not None:  # refused before the ablation folder is made: nothing written
            from mmslam.raytrace.trace import check_cache_root

            c, o = Path(cache_root).resolve(), Path(out).resolve()
            if c != o / "cache" and (c == o or c in o.parents or o in c.parents):
                raise ConfigError(f"--cache {cache_root}: overlaps --out {out}; give a folder of caches apart from "
                                  "the ablation folder (or leave --cache out: the ablation's own is OUT/cache)")
            check_cache_root(cache_root, option="--cache")  # a user's folder
        with locked(out, "ablation"):  # everything checked before the trace; nothing written if refused
            precheck_ablation(out, scn.name, source, steps, particles, sets_c, scn.to_dict())
            start_ablation_dir(out, force)
            cache = prepare_cache(scn, source, out, steps=steps, progress=not quiet, max_depth=max_depth,
                                  samples=samples, cache_root=cache_root)
            cmd = default_command(scenario, vs, mc, particles, source, out, steps, executor, seed0=seed0,
                                  sets=sets_c, grid=grid, scheduler=scheduler, max_depth=max_depth, samples=samples,
                                  truth=truth, cache_root=cache_root)
            run = run_ablation(cache, out, vs, mc=mc, particles=particles, steps=steps, executor=executor,
                               scheduler=scheduler, workers=workers, progress=not quiet, command=cmd,
                               seed0=seed0, sets=sets_c, grid=grid, truth=truth,
                               truth_scenario=_scenario_file(scenario))
            extra = [f"jobs: {len(run.ran)} run, {len(run.skipped)} reused ({run.executor}); wall time "
                     f"{run.wall_time_s:.1f} s",
                     f"summary: {Path(out) / 'summary.parquet'}"]
            extra[:0] = notes
            from mmslam.pipelines.ablate.sensor_models import link_pd_notice

            note = link_pd_notice((run.summary.sensor or {}).get("measurements") or [])
            if note:
                extra.insert(0, note)
            if report:
                from mmslam.pipelines.report import write_report

                extra.append(f"report: {write_report(out)}")
        _print_summary(run.summary, f"{scenario} ({source}), {mc} runs, P = {particles}", extra)

    @app.command("report")
    def report_cmd(
        out: Path = typer.Argument(..., help="An ablation directory (from `mmslam ablate` or `mmslam demo`)."),
    ) -> None:
        """Regenerate the summary, figures and the HTML report from stored results."""
        from mmslam.pipelines.ablate import load_summary
        from mmslam.pipelines.report import write_report

        path = write_report(out)
        _print_summary(load_summary(out), str(out), [f"report: {path}"])
