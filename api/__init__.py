"""The FastAPI job service (the job-service issue)."""
