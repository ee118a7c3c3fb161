"""CLI commands of this subpackage: ``mmslam scene list | build | show | streets``."""
from __future__ import annotations

from pathlib import Path
from typing import Optional

import typer


def register(app: typer.Typer) -> typer.Typer:
    """Add the ``scene`` command group to ``app``; returns it (``raytrace`` adds ``scene coverage``)."""
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
                                 "existing one must be empty or a previous scene build whose files this "
                                 "build replaces are as mmslam wrote them."),
        force: bool = typer.Option(False, "--force/--no-force", help="Accepted for old scripts; changes nothing: "
                                   "a folder mmslam did not write is never written into."),
    ) -> None:
        """Write one PLY per object and a Mitsuba XML that Sionna RT loads (merge_shapes=False)."""
        from mmslam.outputs import check_target, locked, output_kind, record_files, write_marker
        from mmslam.scenes.meshes import SCENE_KIND, build_scene, scene_files
        from mmslam.scenes.scenario import resolve_scenario

        scn = resolve_scenario(scenario)
        names = scene_files(scn)
        with locked(out, "scene build"):
            # before the meshes are made: each file this build writes is absent or as an earlier build wrote it
            check_target(out, SCENE_KIND, force, writes=names)
            xml = build_scene(scn, out)
            if output_kind(out) != SCENE_KIND:
                write_marker(out, SCENE_KIND, files=names)
            else:
                record_files(out, SCENE_KIND, names)
        n = len(scn.buildings) + len(scn.scatterers) + len(scn.vehicles) + (scn.ground is not None)
        typer.echo(f"wrote {xml} ({n} scenario objects, meshes in {xml.parent / 'meshes'})")

    @scene.command("show")
    def show_cmd(
        scenario: str = typer.Argument(..., help="Preset name (paper, street) or a scenario .toml file."),
        out: Path = typer.Option(Path("plan.png"), "--out", help="Figure file for the top-down plan; the "
                                 "format follows the suffix (.png, .pdf, .svg)."),
        force: bool = typer.Option(False, "--force/--no-force", help="Accepted for old scripts; changes nothing: "
                                   "a figure mmslam wrote is replaced anyway, any other file never."),
    ) -> None:
        """Plot a top-down plan: BS, buildings, SPs, VAs, trajectories and FOV circles."""
        from mmslam.outputs import check_figure_target
        from mmslam.scenes.plan import plot_plan
        from mmslam.scenes.scenario import resolve_scenario, scenario_route_points

        from mmslam.scenes.geometry import inside_report
        from mmslam.scenes.trajectory import route_warnings, vehicle_trajectories

        check_figure_target(out, force)
        scn = resolve_scenario(scenario)
        traj = vehicle_trajectories(scn)
        inside = inside_report(scn, traj)
        for who, k, obj, p in inside:
            at = "" if k < 0 else f" at step {k}"
            typer.echo(f"warning: {who}{at} (x={p[0]:.1f}, y={p[1]:.1f}, z={p[2]:.1f}) is inside object '{obj}'; "
                       "marked on the plan, and refused by mmslam trace", err=True)
        for line in route_warnings(scn, traj, scenario_route_points(scn)):
            typer.echo(f"warning: {line}", err=True)
        typer.echo(f"wrote {plot_plan(scn, out, inside=inside)}")

    @scene.command("streets")
    def streets_cmd(
        scene_spec: str = typer.Argument(..., metavar="SCENE",
                                         help="A scenario with an xml_scene (preset or .toml), or an XML scene "
                                              "(sionna:<name> or a .xml file)."),
        out: Path = typer.Option(Path("streets.png"), "--out", help="Figure of the street map; the format follows "
                                 "the suffix (.png, .pdf, .svg). An existing file must be a figure mmslam wrote."),
        data: Optional[Path] = typer.Option(None, "--data", help="Also save the grids (.npz); an existing file "
                                            "must be a street map mmslam wrote."),
        res: float = typer.Option(2.0, "--res", help="Grid resolution (m)."),
        clearance: float = typer.Option(3.0, "--clearance", help="Free space: at least this far from kerbs (m)."),
    ) -> None:
        """Drivable free space (ray-cast height map) and street centrelines of an external scene, drawn and saved.

        With a scenario, its vehicles' routes and the BS are drawn too. Scenarios place cars on
        the streets with `route = [[x, y], ...]` (snapped) or `n_vehicles = N` (seeded random).
        """
        import numpy as np

        from mmslam.errors import ConfigError
        from mmslam.outputs import check_figure_target, check_npz_target, resolve_link
        from mmslam.scenes.geometry import xml_geometry
        from mmslam.scenes.scenario import resolve_scenario, scenario_route_points
        from mmslam.scenes.streets import NPZ_KIND, plot_streets, save_street_map, street_map
        from mmslam.scenes.trajectory import route_warnings, true_trajectories

        if not 0.25 <= res <= 20.0:
            raise ConfigError(f"--res {res}: expected 0.25 .. 20 m")
        if not 0.0 <= clearance <= 50.0:
            raise ConfigError(f"--clearance {clearance}: expected 0 .. 50 m")
        check_figure_target(out)  # both outputs before any work: a file mmslam did not write is never replaced
        if data is not None:
            check_npz_target(data, NPZ_KIND, option="--data")
            if resolve_link(data, "--data").resolve() == resolve_link(out).resolve():
                raise ConfigError(f"--data {data}: the same file as --out; choose two paths")
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
            for line in route_warnings(scn, traj, scenario_route_points(scn)):
                typer.echo(f"warning: {line}", err=True)
        sm = street_map(geom, res=res, clearance=clearance)
        typer.echo(f"wrote {plot_streets(sm, out, f'streets of {title}', routes, bs)} "
                   f"({int(sm.free.sum() * res * res)} m^2 free space, {int(sm.centre.sum())} centreline cells)")
        if data is not None:
            typer.echo(f"wrote {save_street_map(sm, data)}")

    return scene
