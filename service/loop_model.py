"""The closed-loop model of a configured loop, from its latest stiction estimate.

The Nyquist plot, the limit-cycle prediction and the tuning advice all need
the same model: the process identified by the Hammerstein fit, the
controller of the loop's configuration, and the valve of the estimate (the
He or Kano valve the fit chose, with its S and J; a Choudhury valve for an
estimate stored without its model).  Its describing function is thesis
Eq. 3.4 at S and J (``describing="equivalent"``, as the thesis predicts the
He valves of its column, ERRATA item 6).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

from analytics.cycle_fit import ValveKind, valve_of
from analytics.describing import equivalent_sj
from analytics.lti import FirstOrderProcess, TransferFunction
from analytics.simulation import ClosedLoopModel, Loop, PIDController
from analytics.valves import ValveModel
from service.stored import StoredDiagnosis

__all__ = ["IdentifiedLoop", "ModelUnavailableError", "identified_loop", "valve_kind"]


_VALVE_KINDS: dict[str, ValveKind] = {"he": "he", "kano": "kano"}
"""The valve models of the Hammerstein search (:data:`analytics.quantification.VALVE_MODELS`)."""


def valve_kind(valve_model: str | None) -> ValveKind:
    """The valve model an estimate's ``valve_model`` names; Choudhury's for an estimate
    stored without one."""
    return _VALVE_KINDS.get(valve_model or "", "choudhury")


class ModelUnavailableError(LookupError):
    """The loop lacks what a model needs; the message says what (HTTP 404)."""


@dataclass(frozen=True)
class IdentifiedLoop:
    """Process, controller and valve of one loop, in % of span."""

    process: TransferFunction
    controller: PIDController
    valve: ValveModel
    ts: float
    S_interval: tuple[float, float] | None = None
    J_interval: tuple[float, float] | None = None

    @property
    def size(self) -> tuple[float, float]:
        """The valve's ``(S, J)``, % of travel (He's valve: thesis Eq. 1.2)."""
        sj = equivalent_sj(self.valve)
        assert sj is not None  # a He, Kano or Choudhury valve
        return sj

    @property
    def hold_delay(self) -> float:
        """Half a sample: the zero-order hold of the sampled controller."""
        return self.ts / 2.0

    def closed_loop(self, duration: float) -> ClosedLoopModel:
        """The loop as a simulator model, at rest at mid span (no set-point schedule, so
        that :func:`analytics.tuning.excited_model` can step it into its cycle)."""
        return ClosedLoopModel(process=self.process,
                               loops=(Loop(self.controller, self.valve, pv_bias=50.0),),
                               dt=self.ts, duration=duration)


def identified_loop(config: dict[str, Any], diagnosis: StoredDiagnosis | None) -> IdentifiedLoop:
    """The model from a loop's configuration and its latest diagnosis.

    Raises
    ------
    ModelUnavailableError
        No stiction estimate with an identified process, no controller in the
        configuration, or a gain and action that would make positive feedback.
    """
    estimate = None if diagnosis is None else diagnosis.analysis.quantification
    if estimate is None or estimate.S is None or estimate.model is None:
        raise ModelUnavailableError("the latest analysis has no stiction estimate (S, J) "
                                    "with an identified process model")
    controller = config.get("controller")
    if not controller:
        raise ModelUnavailableError("the loop's configuration has no controller (Kc, Ti)")
    process = estimate.model
    action = controller.get("action", "reverse")
    # Reverse action closes negative feedback around a positive process gain.
    gain = process.K if action == "reverse" else -process.K
    if not gain > 0:
        raise ModelUnavailableError(
            f"the identified process gain {process.K:.3g} and the controller action "
            f"'{action}' make positive feedback"
        )
    # A lag shorter than the identification's resolution comes out as tau = 0; the
    # sampled loop still rolls off (hold, transmitter), so it is taken as one
    # sampling interval: negligible at the cycle, and the loop stays strictly proper
    # for the Nyquist count (a PI controller on a pure gain and delay is not).
    tau = process.tau if process.tau > 0 else float(config["ts"])
    return IdentifiedLoop(
        process=FirstOrderProcess(process.kind, gain, tau, process.theta).transfer_function(),
        controller=PIDController.ideal(controller["Kc"], controller.get("Ti") or math.inf,
                                       controller.get("Td", 0.0)),
        valve=valve_of(valve_kind(estimate.valve_model), estimate.S, estimate.J or 0.0),
        ts=float(config["ts"]),
        S_interval=estimate.S_interval,
        J_interval=estimate.J_interval,
    )
