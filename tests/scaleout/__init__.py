"""Scale-out: PostgreSQL at scale, the Dask executor, process roles and leadership."""
