"""Output writers: NetCDF depth profiles, VTK particle series, checkpoints, figures, run.json."""
