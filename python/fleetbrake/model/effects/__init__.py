"""The physical effects the declared model lacks (the vocabulary of ``shared/spec/interface.md``).

Each effect is a small frozen dataclass: its parameters (SI, the unit in the name), its
``name`` in the vocabulary, the *law* it follows (``law``: a family may hold more than one
law under one vocabulary name), the physical ranges its parameters may take
(``PARAMETER_RANGES``: what a test, the synthetic fleet or a fit's starting point draws
from), what is admissible at all (``LIMITS``), and a method that acts *where the effect acts
physically*:

========================  ===============  ========================================  ===============
effect                    law              what it changes                           where it acts
========================  ===============  ========================================  ===============
``friction_speed``        ``karwatzki``    mu(v, F) of cast iron, with its level     heat input
``friction_temperature``  ``linear``       mu fades with the face temperature        heat input (T)
``heat_partition``        ``effusivity``   Charron partition, contact factor         heat input
``convection_speed``      ``power``        h(v) = h0 (1 + a (v / v_ref)^b)           convection
``convection_speed``      ``flat_plate``   h0 + m h(Re, Pr): the block as a plate    convection
``holder_conduction``     ``conductance``  conductance into the holder (back, lug)   convection
``ambient_offset``        ``offset``       air around the block off ambient          ambient
``sensor_lag``            ``first_order``  thermistor lags its seat                  sensor output
``empirical``             ``linear``       a linear correction, tried last           heat input, h
========================  ===============  ========================================  ===============

Laws kept for the revisions stored with them (``candidate = False``: parsed and simulated,
never tried by the close loop):
``friction_speed``/``normalised`` (mu normalised to the registry's), ``heat_partition``/
``alpha`` (the wheel's share itself: the same family as ``effusivity``, reparametrised).
``sensor_lag``/``two_stage`` (seat contact, then the thermistor's body) acts in
:func:`~fleetbrake.model.timeline.simulate_timeline` and in the synthetic generator, but the
chain simulation carries one lag state, so it is not a close-loop candidate
(``candidate = False``) and the chain simulation refuses it rather than drop it.

A law is written ``{"name": ..., "law": ..., "parameters": {...}}`` (:meth:`Effect.to_dict`);
a stored set without ``law`` is read by its parameter names
(:func:`effect_from_dict`): ``friction_speed`` with ``force_exponent`` is the normalised law,
``heat_partition`` with ``alpha`` the plain alpha, and so on.

Usage::

    from fleetbrake.model.effects import ConvectionSpeed, EffectSet, SensorLag, parse_effect

    effects = EffectSet((ConvectionSpeed(gain=2.0, exponent=0.8), SensorLag(tau_s=40.0)))
    text = effects.to_json()                       # '[{"law": "power", "name": ...}, ...]'
    assert EffectSet.from_json(text) == effects
    parse_effect("sensor_lag:tau_s=30")            # the command line's NAME[:k=v,...]
    parse_effect("convection_speed:law=flat_plate,multiplier=0.5")
    SensorLag.random(rng)                          # parameters drawn from PARAMETER_RANGES

The simulation (``fleetbrake.model.timeline.simulate_timeline``) builds :class:`DriveInputs` at
the sample instants (1 Hz), lets :meth:`EffectSet.apply_to_inputs` change them, integrates
the reduced model, and passes its sensor output through :meth:`EffectSet.apply_to_sensor`.
Effects are applied in the fixed order of :data:`EFFECT_CLASSES` whatever order a set was
given in, so that a set means one thing. A set holds each vocabulary name at most once.

:data:`EFFECT_ORDER` is what the close loop tries (every candidate law, ``empirical`` last,
marked ``fallback``: tried only when no physical effect is adequate); :data:`EFFECTS` maps a
vocabulary name to its first law; :data:`LAWS` a name to all its laws.
"""

from fleetbrake.model.effects.base import DriveInputs, Effect
from fleetbrake.model.effects.convection import (
    AmbientOffset,
    ConvectionFlatPlate,
    ConvectionSpeed,
    HolderConduction,
)
from fleetbrake.model.effects.effect_set import EffectSet
from fleetbrake.model.effects.empirical import Empirical
from fleetbrake.model.effects.heat_input import (
    FrictionSpeed,
    FrictionSpeedNormalised,
    FrictionTemperature,
    HeatPartition,
    HeatPartitionEffusivity,
)
from fleetbrake.model.effects.registry import (
    EFFECT_CLASSES,
    EFFECT_ORDER,
    EFFECTS,
    LAWS,
    effect_from_dict,
    find_law,
    parse_effect,
)
from fleetbrake.model.effects.sensor import SensorLag, SensorLagTwoStage

__all__ = [
    "EFFECTS",
    "EFFECT_CLASSES",
    "EFFECT_ORDER",
    "LAWS",
    "AmbientOffset",
    "ConvectionFlatPlate",
    "ConvectionSpeed",
    "DriveInputs",
    "Effect",
    "EffectSet",
    "Empirical",
    "FrictionSpeed",
    "FrictionSpeedNormalised",
    "FrictionTemperature",
    "HeatPartition",
    "HeatPartitionEffusivity",
    "HolderConduction",
    "SensorLag",
    "SensorLagTwoStage",
    "effect_from_dict",
    "find_law",
    "parse_effect",
]
