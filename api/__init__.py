"""The job service's HTTP API (FastAPI): routes, bodies, the job lifecycle and sweeps; it runs no job itself."""
