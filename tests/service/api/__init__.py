"""Tests of the API routes, one module per module of ``service/api/routes/``."""
