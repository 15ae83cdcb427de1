"""Stiction detection: one module per method, a shared evidence contract.

Every detector is a frozen dataclass whose fields are its settings and whose
``detect(window)`` returns a :class:`~analytics.stiction.evidence.MethodEvidence`;
:mod:`analytics.stiction.battery` runs them all and combines their evidence
into one verdict.  Thesis section 1.2.2 reviews the methods.
"""
