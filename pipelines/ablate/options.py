"""Ablation options and the job grid: variants, ``--set`` / ``--grid`` arms, seeds, names on disk.

A job is ``(variant, seed, arm)``; :func:`plan_jobs` spans the grid, :func:`job_dir` says where a
job's result is stored, :func:`default_command` writes the command line that reproduces a run.
"""
from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

from mmslam.errors import ConfigError
from mmslam.executor import EXECUTORS, check_executor
from mmslam.limits import MAX_MC, MAX_PARTICLES, MAX_SEED, MAX_STEPS
from mmslam.slam.specs.landmarks import mapped_types
from mmslam.slam.specs.variants import BUILTIN_VARIANTS, variant_names


VARIANTS: tuple[str, ...] = BUILTIN_VARIANTS
"""Everything an ablation runs by default, in the order it is plotted (the built-in variant specs
of :mod:`mmslam.slam.specs.variants`: the reference ``odometry``, then the filter variants)."""




TYPES: tuple[str, ...] = tuple(s.name for s in mapped_types())
"""Map types scored (the built-in mapped landmark types of :mod:`mmslam.slam.specs.landmarks`)."""


METRIC_QUANTITIES: tuple[str, ...] = ("gospa", "loc", "missed", "false", "n_est", "n_true", "card", "n_visible")


STATE_QUANTITIES: tuple[str, ...] = ("pos_err", "heading_err", "bias_err")


ALL_VEHICLES = "all"
"""``map`` value of the state rows pooled over all vehicles."""


ABLATION_FILE = "ablation.json"


SUMMARY_PARQUET = "summary.parquet"


SUMMARY_JSON = "summary.json"


JOBS_DIR = "jobs"


@dataclass(frozen=True, order=True)
class Job:
    """One filter run: a variant, an explicit seed and the grid arm's parameter settings.

    ``arm`` holds ``section.key=value`` strings of one point of an ``--grid`` (empty without a
    grid); the ablation's ``--set`` overrides apply to every job and are not part of the name.
    """

    variant: str
    seed: int
    arm: tuple[str, ...] = ()

    @property
    def label(self) -> str:
        """The variant, with its grid settings: ``proposed`` or ``proposed[fusion.vs_reduction=gate]``."""
        return arm_label(self.variant, self.arm)

    @property
    def name(self) -> str:
        """Directory name under ``DIR/jobs``: ``<label>-seed<k>``."""
        return f"{self.label}-seed{self.seed}"


def arm_label(variant: str, arm: Sequence[str]) -> str:
    """``variant`` or ``variant[key=value,key2=value2]`` (the summary's ``variant`` column)."""
    return f"{variant}[{','.join(arm)}]" if arm else variant


def parse_label(label: str) -> tuple[str, tuple[str, ...]]:
    """Inverse of :func:`arm_label`."""
    if label.endswith("]") and "[" in label:
        v, _, rest = label.partition("[")
        return v, tuple(x for x in rest[:-1].split(",") if x)
    return label, ()


def _canonical_setting(text: str) -> str:
    """``section.key=value`` with the key and value normalised (``filter.merge = 4`` -> ``filter.merge=4``)."""
    from mmslam.scenes.params import parse_override

    try:
        key, value = parse_override(text)
    except ValueError as e:
        raise ConfigError(str(e)) from None
    if isinstance(value, bool):
        v = str(value).lower()
    elif isinstance(value, (list, tuple)):
        v = "[" + ",".join(str(x) for x in value) + "]"
    else:
        v = str(value)
    if "/" in v or "," in v and not v.startswith("["):
        raise ConfigError(f"--set/--grid {text!r}: value must not contain '/' or ','")
    return f"{key}={v}"


def job_dir(out_dir: str | Path, job: Job) -> Path:
    """Where ``job``'s result is stored."""
    return Path(out_dir) / JOBS_DIR / job.name


def parse_sets(sets: Sequence[str]) -> tuple[str, ...]:
    """``--set`` values (repeatable ``section.key=value``) -> canonical strings, each key once."""
    out = tuple(_canonical_setting(t) for t in sets)
    keys = [t.split("=", 1)[0] for t in out]
    dup = sorted({k for k in keys if keys.count(k) > 1})
    if dup:
        raise ConfigError(f"--set {dup[0]}: given twice; set each parameter once")
    return out


def parse_grid(grid: Sequence[str]) -> list[tuple[str, ...]]:
    """``--grid key=v1,v2`` values (repeatable) -> the arms: every combination, in order.

    No ``--grid`` gives one empty arm ``()``. A grid key may not also be a ``--set`` key (the
    caller checks).
    """
    import itertools

    axes: list[list[str]] = []
    keys: list[str] = []
    for text in grid:
        if "=" not in text:
            raise ConfigError(f"--grid {text!r}: expected section.key=v1,v2 (e.g. fusion.vs_reduction=matched,gate)")
        key, raw = (x.strip() for x in text.split("=", 1))
        vals = [x.strip() for x in raw.split(",") if x.strip()] if not raw.startswith("[") else [raw]
        if not key or not vals:
            raise ConfigError(f"--grid {text!r}: expected section.key=v1,v2 (e.g. fusion.vs_reduction=matched,gate)")
        if key in keys:
            raise ConfigError(f"--grid {key}: given twice; list all its values in one --grid")
        keys.append(key)
        axis = [_canonical_setting(f"{key}={v}") for v in vals]
        if len(set(axis)) != len(axis):
            raise ConfigError(f"--grid {key}: a value is listed twice")
        axes.append(axis)
    return [tuple(c) for c in itertools.product(*axes)] if axes else [()]


def check_grid_clash(sets: Sequence[str], arms: Sequence[tuple[str, ...]]) -> None:
    """One-line :class:`ConfigError` if a ``--grid`` key is also a ``--set`` key (canonical strings)."""
    clash = sorted({a.split("=", 1)[0] for arm in arms for a in arm} & {x.split("=", 1)[0] for x in sets})
    if clash:
        raise ConfigError(f"--grid {clash[0]}: also given with --set; use one of them")


def parse_variants(spec: str | Sequence[str]) -> tuple[str, ...]:
    """``"baseline,cm1"`` or a sequence -> validated tuple (order kept, no duplicates)."""
    items = [s.strip() for s in spec.split(",")] if isinstance(spec, str) else [str(s).strip() for s in spec]
    items = [s for s in items if s]
    if not items:
        raise ConfigError(f"--variants: empty; expected a comma-separated subset of {','.join(variant_names())}")
    for v in items:
        if v not in variant_names():
            raise ConfigError(f"--variants: unknown variant '{v}'; expected a comma-separated subset of "
                              f"{','.join(variant_names())}")
    dup = sorted({v for v in items if items.count(v) > 1})
    if dup:
        raise ConfigError(f"--variants: '{dup[0]}' given twice; list each variant once")
    return tuple(items)


def check_run_args(mc: int, particles: int | None, steps: int | None, executor: str,
                   scheduler: str | None, workers: int | None, seed0: int = 0) -> None:
    """Reject bad numbers / executor settings with a one-line :class:`ConfigError`
    (``particles`` None: the scenario's ``filter.particles``, checked by the scenario)."""
    if not 1 <= int(mc) <= MAX_MC:
        raise ConfigError(f"--mc {mc}: expected 1..{MAX_MC} Monte Carlo runs")
    if not 0 <= int(seed0) <= MAX_SEED - int(mc) + 1:
        raise ConfigError(f"--seed0 {seed0}: expected a seed in 0..{MAX_SEED - int(mc) + 1} (seeds seed0..seed0+mc-1)")
    if particles is not None and not 1 <= int(particles) <= MAX_PARTICLES:
        raise ConfigError(f"--particles {particles}: expected 1..{MAX_PARTICLES} particles")
    if steps is not None and not 1 <= int(steps) <= MAX_STEPS:
        raise ConfigError(f"--steps {steps}: expected 1..{MAX_STEPS} time steps")
    check_executor(executor, scheduler, workers)


def plan_jobs(variants: Sequence[str], mc: int, seed0: int = 0,
              arms: Sequence[tuple[str, ...]] = ((),)) -> list[Job]:
    """The grid ``variants x arms x seeds seed0..seed0+mc-1``, variant-major."""
    return [Job(v, s, tuple(a)) for v in variants for a in arms for s in range(int(seed0), int(seed0) + int(mc))]


def is_finished(out_dir: str | Path, job: Job) -> bool:
    """True if ``job``'s result directory is complete (``Result.save`` is atomic)."""
    d = job_dir(out_dir, job)
    return (d / "meta.json").is_file() and all((d / f"{t}.parquet").is_file()
                                               for t in ("vehicles", "metrics", "landmarks"))


def default_command(scenario: str, variants: Sequence[str], mc: int, particles: int, source: str | None,
                    out: Path, steps: int | None, executor: str = "local", seed0: int = 0,
                    sets: Sequence[str] = (), grid: Sequence[str] = (), scheduler: str | None = None,
                    max_depth: int = 1, samples: int = 1_000_000, truth: str = "per-run",
                    cache_root: Path | None = None) -> str:
    """The ``mmslam ablate`` command line that reproduces an ablation (with its ``--scheduler``, and the trace's
    ``--max-depth`` / ``--samples``, ``--truth`` and ``--cache`` where they are not the defaults)."""
    import shlex

    argv = ["mmslam", "ablate", scenario, "--variants", ",".join(variants), "--mc", str(mc),
            "--particles", str(particles), "--source", str(source or "analytic"), "--out", str(out)]
    if steps is not None:
        argv += ["--steps", str(steps)]
    if seed0:
        argv += ["--seed0", str(seed0)]
    for x in sets:
        argv += ["--set", x]
    for x in grid:
        argv += ["--grid", x]
    if int(max_depth) != 1:
        argv += ["--max-depth", str(int(max_depth))]
    if int(samples) != 1_000_000:
        argv += ["--samples", str(int(samples))]
    if truth != "per-run":
        argv += ["--truth", str(truth)]
    if cache_root is not None:
        argv += ["--cache", str(cache_root)]
    if executor != "local":
        argv += ["--executor", executor]
    if executor != "local" and scheduler:
        argv += ["--scheduler", scheduler]
    return shlex.join(argv)
