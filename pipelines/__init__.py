"""User-facing jobs: demo, Monte Carlo ablations (local process pool or Dask), figures, report."""
