"""The REST API (FastAPI, ``/api/v1``): thin routes over the service modules."""
