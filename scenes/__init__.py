"""Scenario model, presets, ground-truth trajectories and landmarks, scene meshes (no Sionna import)."""
from mmslam.scenes.scenario import Scenario, list_presets, load_preset, load_scenario, resolve_scenario

__all__ = ["Scenario", "list_presets", "load_preset", "load_scenario", "resolve_scenario"]
