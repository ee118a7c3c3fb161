"""CLI commands of this subpackage: ``mmslam scene list | build | show``."""
from __future__ import annotations

from pathlib import Path

import typer


def register(app: typer.Typer) -> None:
    """Add the ``scene`` command group to ``app``."""
    scene = typer.Typer(no_args_is_help=True, help="Scenario presets, scene meshes (PLY + Mitsuba XML), plan plots.")
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

    @scene.command("build")
    def build_cmd(
        scenario: str = typer.Argument(..., help="Preset name (paper, street) or a scenario .toml file."),
        out: Path = typer.Option(..., "--out", help="Output folder for meshes/*.ply and <scenario>.xml."),
    ) -> None:
        """Write one PLY per object and a Mitsuba XML that Sionna RT loads (merge_shapes=False)."""
        from mmslam.scenes.meshes import build_scene
        from mmslam.scenes.scenario import resolve_scenario

        scn = resolve_scenario(scenario)
        xml = build_scene(scn, out)
        n = len(scn.buildings) + len(scn.scatterers) + len(scn.vehicles) + (scn.ground is not None)
        typer.echo(f"wrote {xml} ({n} scenario objects, meshes in {xml.parent / 'meshes'})")

    @scene.command("show")
    def show_cmd(
        scenario: str = typer.Argument(..., help="Preset name (paper, street) or a scenario .toml file."),
        out: Path = typer.Option(Path("plan.png"), "--out", help="PNG file for the top-down plan."),
    ) -> None:
        """Plot a top-down plan: BS, buildings, SPs, VAs, trajectories and FOV circles."""
        from mmslam.scenes.meshes import plot_plan
        from mmslam.scenes.scenario import resolve_scenario

        scn = resolve_scenario(scenario)
        typer.echo(f"wrote {plot_plan(scn, out)}")
