"""Path sources (Sionna RT, analytic), path labels and the resumable Parquet path cache.

Only :mod:`mmslam.raytrace.sionna_adapter` imports Sionna; the rest is NumPy / pyarrow.
"""
