"""mmslam: ray-traced mmWave multipath datasets and cooperative MM-PHD-SLAM with moving scatterers.

Subpackages (folders at the repository top level):

- :mod:`mmslam.scenes`    scenario model, presets, trajectories, meshes + Mitsuba XML
- :mod:`mmslam.raytrace`  Sionna RT / analytic path sources, labels, the Parquet path cache
- :mod:`mmslam.slam`      sensor model, MM-PHD-SLAM filter variants, map fusion, GOSPA
- :mod:`mmslam.pipelines` demo, Monte Carlo ablations (local or Dask), figures, HTML report

Importing :mod:`mmslam.slam` never imports Sionna, Mitsuba or Dr.Jit.
"""
__version__ = "0.1.0"
"""The package version: the only place it is written (pyproject.toml reads it, ``mmslam --version`` prints it)."""
