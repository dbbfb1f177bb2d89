"""The API's routes, one ``APIRouter`` per module: jobs, metrics, service, sweeps."""
