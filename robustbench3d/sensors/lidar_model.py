"""HDL-64E return model: which ray hits give a return, their range noise and their reflectance.

Fitted by eye to the six real KITTI scans; used by the generator (:mod:`robustbench3d.synth.lidar`)
and meant to be used by anything else that renders into a scan. Ranges in m along unit rays from the
laser's origin (:class:`~robustbench3d.sensors.hdl64e.HDL64E`); vectors in any one frame (the
generator uses velodyne). All functions are vectorised over N hits; the random parts take a
``numpy.random.Generator`` and draw exactly the numbers the generator draws, in the same order
when called in the order of :func:`robustbench3d.synth.lidar.simulate_scan`.

The model of one revolution:

1. Range gate: a hit counts if ``MIN_RANGE_M < t <= MAX_RANGE_M`` (:func:`in_range`).
2. Return or not: with probability ``return_prob(material) * sigmoid(ln(S / S0) / 0.5)`` for the
   received signal ``S = rho * max(cos(incidence), 0.02) / t^2`` and ``S0 = 3.9e-6``
   (:func:`return_probability`): grazing asphalt fades out around 50-60 m, walls and cars return up to
   120 m. There is no hard incidence cut-off; the 0.02 floor keeps grazing hits faintly visible.
3. Range noise: Gaussian along the ray, sd 1 cm clipped at 3 cm (:func:`range_noise`); the point stays
   on its laser's cone.
4. Reflectance: ``rho * (0.55 + 0.45 cos(incidence)) * level(r)`` (:func:`reflectance_mean`) times
   12 % log-normal noise (:func:`reflectance_noise`), reported as 0 with probability
   :func:`zero_reflectance_probability` (about 5 % below 25 m, half at 45 m, 90 % beyond 60 m),
   quantised down to 0.01 and kept in [0, 0.99] (:func:`quantize_reflectance`).

``rho`` is the surface's reflectivity in [0, 0.98] (:func:`material_reflectivity`: from the material
table, scaled by the albedo's brightness for :data:`~robustbench3d.sensors.materials.TINTED`
materials; the generator's terrain sets it per point instead).
"""

from __future__ import annotations

import numpy as np

from robustbench3d.sensors.hdl64e import MAX_RANGE_M
from robustbench3d.sensors.materials import REFLECTIVITY, TINTED

#: Received signal at which half the pulses return (reflectivity / m^2).
SIGNAL_THRESHOLD = 3.9e-6
#: Width of the return probability's sigmoid in ln(signal).
SIGNAL_LOG_WIDTH = 0.5
#: Floor of |cos(incidence)| in the received signal.
MIN_COS_INCIDENCE = 0.02
#: Standard deviation of the range noise, m (clipped at 3 sd).
RANGE_NOISE_SD = 0.01
#: Returns closer than this are discarded, m (the real scans start at about 1.4 m).
MIN_RANGE_M = 1.0
#: Standard deviation of ln(reflectance noise factor).
REFLECTANCE_NOISE_SD = 0.12
#: Largest surface reflectivity.
MAX_REFLECTIVITY = 0.98
#: Largest reported reflectance (the scan stores multiples of 0.01 in [0, 0.99]).
MAX_REFLECTANCE = 0.99
#: Rec. 709 luminance weights of linear RGB.
LUMINANCE_WEIGHTS = np.array([0.2126, 0.7152, 0.0722], dtype=np.float32)

__all__ = [
    "LUMINANCE_WEIGHTS", "MAX_RANGE_M", "MAX_REFLECTANCE", "MAX_REFLECTIVITY", "MIN_COS_INCIDENCE", "MIN_RANGE_M",
    "RANGE_NOISE_SD", "REFLECTANCE_NOISE_SD", "SIGNAL_LOG_WIDTH", "SIGNAL_THRESHOLD", "albedo_luminance",
    "cos_incidence", "in_range", "material_reflectivity", "quantize_reflectance", "range_attenuation",
    "range_noise", "received_signal", "reflectance_mean", "reflectance_noise", "return_probability", "sigmoid",
    "tint_factor", "zero_reflectance_probability",
]


def sigmoid(x: np.ndarray) -> np.ndarray:
    """Logistic function 1 / (1 + exp(-x)), written with tanh (no overflow)."""
    return 0.5 * (1.0 + np.tanh(0.5 * x))


def in_range(t: np.ndarray) -> np.ndarray:
    """(N,) bool: hit distances ``t`` (m) inside the sensor's range gate (MIN_RANGE_M, MAX_RANGE_M]."""
    return (t > MIN_RANGE_M) & (t <= MAX_RANGE_M)


def cos_incidence(normals: np.ndarray, directions: np.ndarray) -> np.ndarray:
    """(N,) |cos| of the angle between unit face normals (N, 3) and unit ray directions (N, 3), same frame
    (two-sided: the normal's orientation does not matter)."""
    return np.abs(normals[:, 0] * directions[:, 0] + normals[:, 1] * directions[:, 1]
                  + normals[:, 2] * directions[:, 2])


def albedo_luminance(albedo: np.ndarray) -> np.ndarray:
    """(N,) float32 luminance of linear-RGB albedos (N, 3) in [0, 1]."""
    return albedo @ LUMINANCE_WEIGHTS


def tint_factor(luminance: np.ndarray) -> np.ndarray:
    """Reflectivity multiplier 0.55 + 0.9 sqrt(luminance) of a tinted material (0.55 black, 1.45 white)."""
    return 0.55 + 0.9 * np.sqrt(luminance)


def material_reflectivity(material: np.ndarray, albedo: np.ndarray) -> np.ndarray:
    """(N,) float32 reflectivity rho in [0, 0.98] of hits on faces of ``material`` (N,) ids
    (:class:`~robustbench3d.sensors.materials.Mat`) and linear-RGB ``albedo`` (N, 3) float32: the material's
    reflectivity, times :func:`tint_factor` of the albedo's luminance for tinted materials (car paint,
    facades, walls, cloth)."""
    rho = REFLECTIVITY[material]
    lum = albedo_luminance(albedo)
    tinted = TINTED[material]
    rho[tinted] *= tint_factor(lum[tinted])
    return np.clip(rho, 0.0, MAX_REFLECTIVITY)


def received_signal(reflectivity: np.ndarray, cos_inc: np.ndarray, t: np.ndarray) -> np.ndarray:
    """Received pulse energy rho * max(cos(incidence), 0.02) / t^2 (reflectivity / m^2) at distance t (m)."""
    return reflectivity * np.maximum(cos_inc, MIN_COS_INCIDENCE) / (t * t)


def return_probability(return_prob: np.ndarray, reflectivity: np.ndarray, cos_inc: np.ndarray,
                       t: np.ndarray) -> np.ndarray:
    """(N,) probability that a hit produces a return: the material's ``return_prob``
    (:data:`~robustbench3d.sensors.materials.RETURN_PROB`) times sigmoid(ln(S / SIGNAL_THRESHOLD) / 0.5) of the
    :func:`received_signal` S of reflectivity rho, |cos(incidence)| and distance t (m)."""
    signal = received_signal(reflectivity, cos_inc, t)
    return return_prob * sigmoid(np.log(np.maximum(signal, 1e-30) / SIGNAL_THRESHOLD) / SIGNAL_LOG_WIDTH)


def range_noise(rng: np.random.Generator, n: int) -> np.ndarray:
    """(n,) range errors, m, added to the hit distance along the ray: N(0, 1 cm) clipped at +-3 cm."""
    return np.clip(rng.normal(0.0, RANGE_NOISE_SD, n), -3 * RANGE_NOISE_SD, 3 * RANGE_NOISE_SD)


def range_attenuation(r: np.ndarray) -> np.ndarray:
    """Reflectance level at measured range r (m): 1 up to 20 m, then -1.2 % per m, at least 0.3."""
    return np.clip(1.0 - 0.012 * np.maximum(r - 20.0, 0.0), 0.3, 1.0)


def reflectance_mean(reflectivity: np.ndarray, cos_inc: np.ndarray, r: np.ndarray) -> np.ndarray:
    """Reflectance before noise and quantisation: rho * (0.55 + 0.45 |cos(incidence)|) * level(r), r in m
    (normal incidence below 20 m gives rho, grazing incidence 0.55 rho)."""
    return reflectivity * (0.55 + 0.45 * cos_inc) * range_attenuation(r)


def reflectance_noise(rng: np.random.Generator, n: int) -> np.ndarray:
    """(n,) multiplicative log-normal reflectance noise exp(N(0, 0.12))."""
    return np.exp(rng.normal(0.0, REFLECTANCE_NOISE_SD, n))


def zero_reflectance_probability(r: np.ndarray) -> np.ndarray:
    """Probability 0.04 + 0.9 sigmoid((r - 45) / 5) that a return at range r (m) reports reflectance 0."""
    return 0.04 + 0.9 * sigmoid((r - 45.0) / 5.0)


def quantize_reflectance(reflectance: np.ndarray, zero: np.ndarray) -> np.ndarray:
    """Reported reflectance: 0 where ``zero`` (bool), else rounded down to 0.01 and kept in [0, 0.99]."""
    return np.where(zero, 0.0, np.clip(np.floor(reflectance * 100.0) / 100.0, 0.0, MAX_REFLECTANCE))
