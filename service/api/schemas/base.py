"""The base of the response models: a field's docstring is its OpenAPI description."""

from __future__ import annotations

from pydantic import BaseModel, ConfigDict


class Schema(BaseModel):
    """A response model whose field docstrings describe the fields in ``/openapi.json``."""

    model_config = ConfigDict(use_attribute_docstrings=True)


class OpenSchema(Schema):
    """A response model that keeps fields it does not name (``extra="allow"``): for
    results stored as JSON, which other versions of the analysis wrote with more or
    fewer keys."""

    model_config = ConfigDict(extra="allow")
