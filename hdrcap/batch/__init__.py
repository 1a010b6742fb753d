"""Many runs merged on dask.distributed (one task per run, the same merge as ``hdrcap merge``)
into a zarr archive that xarray opens; ``hdrcap export`` writes one run back as an EXR."""
