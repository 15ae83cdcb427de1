"""Response models of the API's analytics answers, one module per area.

They document field by field, in ``/openapi.json``, what the routes return
(the JSON forms of :mod:`analytics` results plus what the service adds).  The
routes still build their answers as dicts; FastAPI validates them against
these models and serializes what is set (``response_model_exclude_unset``: a
key absent from the dict stays absent).  ``tests/service/api/test_schemas.py``
checks that every answer keeps every key it had without the models.
"""
