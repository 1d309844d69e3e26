"""Ready-made rig physics resembling the paper's transducers (Sec. 5), for tests and emulators.

The paper reports k_f = 0.291e8 N/m, b_f = 17136 N*s/m (5 kN) and 0.246e8 N/m, 3032 N*s/m
(12.5 kN) with a 25.717 kg top mass; end and adaption masses are not given there, the values below
are typical for such transducers.
"""

from __future__ import annotations

from dataclasses import replace

from drivers.rig.params import Adc, Conditioner, DisplacementSensor, Effects, RigPhysics, Transducer

TOP_MASS_KG = 25.717
ADAPTION_MASS_KG = 0.45


def paper_5kN_physics(effects: Effects | None = None, *, noise: bool = True) -> RigPhysics:
    """The 5 kN transducer of the paper's Experiment I on the simulated rig."""
    return _physics(Transducer(k_f=2.91e7, b_f=17136.0, m_e=0.12, m_l=TOP_MASS_KG + ADAPTION_MASS_KG,
                               sensitivity_V_per_N=2.0e-6, capacity_N=5000.0), effects, noise)


def paper_12k5N_physics(effects: Effects | None = None, *, noise: bool = True) -> RigPhysics:
    """The 12.5 kN transducer of the paper's Experiment II on the simulated rig."""
    return _physics(Transducer(k_f=2.46e7, b_f=3032.0, m_e=0.25, m_l=TOP_MASS_KG + ADAPTION_MASS_KG,
                               sensitivity_V_per_N=0.8e-6, capacity_N=12500.0), effects, noise)


def _physics(t: Transducer, effects: Effects | None, noise: bool) -> RigPhysics:
    ph = RigPhysics(
        transducer=t,
        displacement_sensor=DisplacementSensor(gain_V_per_m=500.0, noise_m=2e-7),
        conditioner=Conditioner(gain=1000.0, offset_V=0.0, noise_V=5e-4),
        adc=Adc(bits=16, displacement_range_V=10.0, force_range_V=10.0),
        effects=effects or Effects(),
    )
    if not noise:
        ph = replace(ph, displacement_sensor=replace(ph.displacement_sensor, noise_m=0.0),
                     conditioner=replace(ph.conditioner, noise_V=0.0))
    return ph
