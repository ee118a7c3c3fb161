"""CLI commands of this subpackage: ``mmslam scene list | build | show | streets``."""
from __future__ import annotations

from pathlib import Path
from typing import Optional

import typer


def register(app: typer.Typer) -> None:
    """Add the ``scene`` command group to ``app``."""
    scene = typer.Typer(no_args_is_help=True, rich_markup_mode=None,
                        help="Scenario presets, scene meshes (PLY + Mitsuba XML), plan plots.")
    app.add_typer(scene, name="scene")

    @scene.command("list")
    def list_cmd() -> None:
        """List the shipped presets: name, vehicles, buildings, scatterers, steps."""
        from mmslam.scenes.scenario import list_presets, load_preset

        for name in list_presets():
            s = load_preset(name)
            extra = f", xml_scene {s.xml_scene}" if s.xml_scene else ""
            ground = ", ground" if s.ground is not None else ""
            typer.echo(f"{name}: {len(s.vehicles)} vehicles, {len(s.buildings)} buildings, "
                       f"{len(s.scatterers)} scatterers{ground}, {s.steps} steps of {s.dt:g} s{extra}")

    @scene.command("reference")
    def reference_cmd() -> None:
        """Print the scenario-file reference (Markdown): every key, default, unit, bounds (docs/scenario.md)."""
        from mmslam.scenes.scenario import scenario_reference

        typer.echo(scenario_reference(), nl=False)

    @scene.command("build")
    def build_cmd(
        scenario: str = typer.Argument(..., help="Preset name (paper, street) or a scenario .toml file."),
        out: Path = typer.Option(..., "--out", help="Output folder for meshes/*.ply and <scenario>.xml; an "
                                 "existing one must be empty or a previous scene build."),
        force: bool = typer.Option(False, "--force/--no-force", help="Write into --out even if it is not a "
                                   "previous scene build (files of the same names are replaced)."),
    ) -> None:
        """Write one PLY per object and a Mitsuba XML that Sionna RT loads (merge_shapes=False)."""
        from mmslam.outputs import check_target, locked, output_kind, write_marker
        from mmslam.scenes.meshes import SCENE_KIND, build_scene
        from mmslam.scenes.scenario import resolve_scenario

        scn = resolve_scenario(scenario)
        with locked(out, "scene build"):
            check_target(out, SCENE_KIND, force, force_does="write into it")  # before the meshes are made
            xml = build_scene(scn, out)
            if output_kind(out) != SCENE_KIND:
                write_marker(out, SCENE_KIND)
        n = len(scn.buildings) + len(scn.scatterers) + len(scn.vehicles) + (scn.ground is not None)
        typer.echo(f"wrote {xml} ({n} scenario objects, meshes in {xml.parent / 'meshes'})")

    @scene.command("show")
    def show_cmd(
        scenario: str = typer.Argument(..., help="Preset name (paper, street) or a scenario .toml file."),
        out: Path = typer.Option(Path("plan.png"), "--out", help="Figure file for the top-down plan; the "
                                 "format follows the suffix (.png, .pdf, .svg)."),
        force: bool = typer.Option(False, "--force/--no-force", help="Replace --out even if it is not a figure "
                                   "mmslam wrote."),
    ) -> None:
        """Plot a top-down plan: BS, buildings, SPs, VAs, trajectories and FOV circles."""
        from mmslam.outputs import check_figure_target
        from mmslam.scenes.meshes import plot_plan
        from mmslam.scenes.scenario import resolve_scenario

        from mmslam.scenes.geometry import inside_report
        from mmslam.scenes.trajectory import vehicle_trajectories

        check_figure_target(out, force)
        scn = resolve_scenario(scenario)
        inside = inside_report(scn, vehicle_trajectories(scn))
        for who, k, obj, p in inside:
            at = "" if k < 0 else f" at step {k}"
            typer.echo(f"warning: {who}{at} (x={p[0]:.1f}, y={p[1]:.1f}, z={p[2]:.1f}) is inside object '{obj}'; "
                       "marked on the plan, and refused by mmslam trace", err=True)
        typer.echo(f"wrote {plot_plan(scn, out, inside=inside)}")

    @scene.command("streets")
    def streets_cmd(
        scene_spec: str = typer.Argument(..., metavar="SCENE",
                                         help="A scenario with an xml_scene (preset or .toml), or an XML scene "
                                              "(sionna:<name> or a .xml file)."),
        out: Path = typer.Option(Path("streets.png"), "--out", help="PNG of the street map."),
        data: Optional[Path] = typer.Option(None, "--data", help="Also save the grids (.npz)."),
        res: float = typer.Option(2.0, "--res", help="Grid resolution (m)."),
        clearance: float = typer.Option(3.0, "--clearance", help="Free space: at least this far from kerbs (m)."),
    ) -> None:
        """Drivable free space (ray-cast height map) and street centrelines of an external scene, drawn and saved.

        With a scenario, its vehicles' routes and the BS are drawn too. Scenarios place cars on
        the streets with `route = [[x, y], ...]` (snapped) or `n_vehicles = N` (seeded random).
        """
        import numpy as np

        from mmslam.errors import ConfigError
        from mmslam.scenes.geometry import xml_geometry
        from mmslam.scenes.scenario import resolve_scenario
        from mmslam.scenes.streets import plot_streets, save_street_map, street_map
        from mmslam.scenes.trajectory import true_trajectories

        if not 0.25 <= res <= 20.0:
            raise ConfigError(f"--res {res}: expected 0.25 .. 20 m")
        if not 0.0 <= clearance <= 50.0:
            raise ConfigError(f"--clearance {clearance}: expected 0 .. 50 m")
        routes, bs = {}, None
        if scene_spec.startswith("sionna:") or scene_spec.endswith(".xml"):
            geom, title = xml_geometry(scene_spec), scene_spec
        else:
            scn = resolve_scenario(scene_spec)
            if not scn.xml_scene:
                raise ConfigError(f"{scn.source_file}: no xml_scene; streets are computed for external city scenes "
                                  "(e.g. xml_scene = \"sionna:munich\")")
            geom, title, bs = xml_geometry(scn.xml_scene, scn.source_file), f"{scn.name} ({scn.xml_scene})", scn.bs_array
            traj = true_trajectories(scn)
            routes = {v.name: traj[:, i, :2] for i, v in enumerate(scn.vehicles)}
        sm = street_map(geom, res=res, clearance=clearance)
        typer.echo(f"wrote {plot_streets(sm, out, f'streets of {title}', routes, bs)} "
                   f"({int(sm.free.sum() * res * res)} m^2 free space, {int(sm.centre.sum())} centreline cells)")
        if data is not None:
            typer.echo(f"wrote {save_street_map(sm, data)}")

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
        force: bool = typer.Option(False, "--force/--no-force", help="Replace --out even if it is not a figure "
                                   "mmslam wrote."),
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
