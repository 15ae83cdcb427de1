"""Domain errors of the numerical core.

They derive from :class:`ValueError` so that callers which only know the
standard library still catch them; the service translates them to HTTP 422
at the API edge.
"""


class AnalyticsError(ValueError):
    """Base class of every error raised by :mod:`analytics`."""


class ValveModelError(AnalyticsError):
    """Invalid valve (stiction) model parameters or input."""


class ModelSpecError(AnalyticsError):
    """Invalid process, controller or loop specification."""


class DataError(AnalyticsError):
    """Measured data that cannot be analysed (NaN, too short, not increasing...)."""
