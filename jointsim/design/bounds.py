"""Fisher information and Cramér–Rao bounds of a press, from its derivatives.

The instrument measures the reference frame (the untouched sensor, ``reference_frames`` frames
averaged) and a frame of the press (``hold_frames`` averaged, the target held still), each
channel with white Gaussian noise of std σ per frame. For the parameters φ = (θ, η), θ the
target's and η the sensor's nuisances, the Fisher information is

    F = (R · J_refᵀ J_ref + H · J_kᵀ J_k) / σ²,

(the target does not touch the reference: its columns of J_ref are zero). Bounds on the
target's parameters, as covariances (m²):

- **nuisances known**: (F_θθ)⁻¹;
- **nuisances marginalised**: [(F + Λ)⁻¹]_θθ, with Λ = diag(1/s²) the nuisances' prior
  information: s is the spread the scene's own domain randomisation gives each of them
  ([dataset]: membrane_scale, conductivity_s_per_m, contact_impedance_ohm_m2,
  electrode_jitter_mm; the reservoir head, which no dataset varies, ±20 % (ASSUMED)). Without a
  prior some are not identifiable at all: the moduli and the head act on a depth-controlled
  press only as their ratio (:mod:`.sensitivity`), and a rotation of every electrode about the
  axis is a rotation of the target.

An unbiased estimator's error covariance is at least the bound; the scalar figures are the
RMS error it allows: position √(C_xx + C_yy), depth √C_dd, diameter 2√C_RR. An efficient
estimator's median |error| is 0.674× the RMS in one dimension and, in the plane, between 0.674×
(the error along one axis) and 0.833× (isotropic: 1.177σ against an RMS of √2σ);
:func:`median_error` gives it for a covariance, which is what the goals (medians) are held to.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from ..scene import Scene
from .sensitivity import TARGET, target_names

__all__ = ["HEAD_PRIOR", "Bounds", "nuisance_prior", "fisher", "press_fisher", "press_bounds", "joint_bounds", "median_error"]

HEAD_PRIOR = 0.2  # ln of the reservoir head: ±20 % (1 mm of a 5 mm saline column; ASSUMED)


def _uniform_std(lo: float, hi: float) -> float:
    return (hi - lo) / math.sqrt(12.0)


def nuisance_prior(scene: Scene, names: tuple[str, ...]) -> np.ndarray:
    """The prior std of each nuisance in ``names`` (those after the target's), in its unit (ln,
    or m for an electrode's centre): the spread of the scene's [dataset] randomisation (a uniform
    range's std; a log-uniform one's std of ln; a disc of radius r: r/2 per coordinate). 0 marks
    a parameter the scene holds exact (known)."""
    d = scene.dataset
    flat = scene.membrane.moulding == "flat"
    out = []
    for n in names[len(target_names(names)):]:
        if n == "ln_pressure":
            out.append(0.0 if flat else HEAD_PRIOR)
        elif n == "ln_modulus":
            out.append(_uniform_std(*np.log(d.membrane_scale)))
        elif n == "ln_conductivity":
            out.append(_uniform_std(*d.conductivity) / float(np.mean(d.conductivity)))
        elif n.startswith("ln_z"):
            out.append(_uniform_std(*np.log(d.contact_impedance)))
        else:  # an electrode's x or y
            out.append(d.electrode_jitter / 2)
    return np.asarray(out, float)


def fisher(info_ref: np.ndarray, info: np.ndarray, noise_std: float, *, reference_frames: int,
           hold_frames: int = 1) -> np.ndarray:
    """F (P, P) (module docstring) from the reference's and the frame's information at unit
    noise, ``info_ref`` = J_refᵀJ_ref and ``info`` = J_kᵀJ_k (P, P), and one frame's
    ``noise_std`` V."""
    return (reference_frames * np.asarray(info_ref) + hold_frames * np.asarray(info)) / (noise_std * noise_std)


def press_fisher(info_ref: np.ndarray, infos: np.ndarray, noise_std: float, *, reference_frames: int,
                 hold_frames: int = 1) -> np.ndarray:
    """F of a press's K frames read together: the target's x, y and radius and the nuisances are
    the same in every frame, each frame has a depth of its own. ``infos`` (K, P, P) are the
    frames' J_kᵀJ_k, ``info_ref`` the reference's, at unit noise. The parameters are ordered as
    :func:`fisher`'s with the deepest frame's depth in the depth slot, then the other frames'
    depths (P + K − 1 in all), so :func:`press_bounds` reads them as one frame's, the extra
    depths given no prior (``inf``)."""
    infos = np.asarray(infos, float)
    K, P = infos.shape[0], infos.shape[1]
    depth = TARGET.index("depth")
    F = np.zeros((P + K - 1, P + K - 1))
    F[:P, :P] = reference_frames * np.asarray(info_ref, float)
    for k in range(K):
        idx = np.arange(P)
        if k < K - 1:
            idx[depth] = P + k
        F[np.ix_(idx, idx)] += hold_frames * infos[k]
    return F / (noise_std * noise_std)


def _inverse(F: np.ndarray) -> np.ndarray:
    """F⁻¹ of a symmetric positive semi-definite F, scaled to unit diagonal first (the parameters
    span metres to logarithms), by Cholesky; inf where F is not numerically positive definite
    (a direction the data and the prior leave free). Not an eigenvalue threshold: the head and
    the modulus enter only as their ratio, so at a high SNR the prior is all that separates
    them, 1e-13 of the data's information, and the bound is still finite and exact."""
    d = np.sqrt(np.clip(np.diag(F), 0.0, None))
    if not (d > 0).all():
        return np.full(F.shape, np.inf)
    S = F / np.outer(d, d)
    try:
        L = np.linalg.cholesky(S)
    except np.linalg.LinAlgError:
        return np.full(F.shape, np.inf)
    Linv = np.linalg.solve(L, np.eye(len(S)))
    return (Linv.T @ Linv) / np.outer(d, d)


@dataclass(frozen=True)
class Bounds:
    """Cramér–Rao bounds of the target's parameters (:func:`~.sensitivity.target_names`: x, y,
    depth, radius and a soft target's ln E) at one depth of a press: covariances ``known`` and
    ``marginal`` (t, t) in m² (and ln² for ln E; nuisances known / marginalised over their
    prior), and ``contact_known``, ``contact_marginal`` (2, 2): the same for the contact's
    centre of pressure in the plane (through its derivative)."""

    known: np.ndarray
    marginal: np.ndarray
    contact_known: np.ndarray
    contact_marginal: np.ndarray

    def rms(self, which: str = "marginal") -> dict[str, float]:
        """RMS errors m the bound allows: ``position`` (the target's centre), ``contact`` (the
        contact point), ``depth``, ``diameter``; for a soft target ``modulus``, the RMS of ln E
        (the relative error of E, to first order)."""
        C = getattr(self, which)
        Cc = getattr(self, f"contact_{which}")
        out = {"position": math.sqrt(C[0, 0] + C[1, 1]), "contact": math.sqrt(np.trace(Cc)),
               "depth": math.sqrt(C[2, 2]), "diameter": 2 * math.sqrt(C[3, 3])}
        if len(C) > len(TARGET):
            out["modulus"] = math.sqrt(C[4, 4])
        return out


def press_bounds(F: np.ndarray, prior_std: np.ndarray, contact_jacobian: np.ndarray) -> Bounds:
    """The :class:`Bounds` of Fisher information ``F`` (P, P) with the nuisances' ``prior_std``
    (P − t,) (0: known, dropped; inf: no prior) and the contact's ``contact_jacobian`` (2, t),
    t the target's parameters (4, or 5 with a soft target's modulus)."""
    t = np.shape(contact_jacobian)[-1]
    keep = np.concatenate([np.ones(t, bool), prior_std > 0])
    prior = np.concatenate([np.zeros(t), 1.0 / np.square(prior_std[prior_std > 0])])
    known = _inverse(F[:t, :t])
    marginal = _inverse(F[np.ix_(keep, keep)] + np.diag(prior))[:t, :t]
    G = np.asarray(contact_jacobian, float)

    def through(C: np.ndarray) -> np.ndarray:  # an unbounded parameter leaves the contact unbounded
        return G @ C @ G.T if np.isfinite(C).all() else np.full((2, 2), np.inf)
    return Bounds(known, marginal, through(known), through(marginal))


def joint_bounds(F: np.ndarray, prior_std: np.ndarray, contact_jacobian: np.ndarray) -> Bounds:
    """:func:`press_bounds` of a press's frames read together (:func:`press_fisher`), whose
    parameters after the nuisances are the other frames' depths (``prior_std`` inf there): the
    target's, so free in both kinds; the nuisances-known bound drops the nuisances alone."""
    t, n_extra = np.shape(contact_jacobian)[-1], int(np.isinf(prior_std).sum())
    marginal = press_bounds(F, prior_std, contact_jacobian)
    keep = np.r_[np.arange(t), len(prior_std) + t - n_extra + np.arange(n_extra)]
    known = press_bounds(F[np.ix_(keep, keep)], np.full(n_extra, np.inf), contact_jacobian)
    return Bounds(known.marginal, marginal.marginal, known.contact_marginal, marginal.contact_marginal)


_NORMALS = np.random.default_rng(12345).standard_normal((2, 20001))  # fixed: the median below is deterministic


def median_error(C: np.ndarray) -> float:
    """The median |e| of a zero-mean Gaussian error e with covariance ``C`` (1×1 or 2×2): what an
    efficient estimator's median error is (0.674√C in 1-D; the 2-D one from its eigenvalues,
    by a fixed sample of 20001 normals: ±1 % at worst)."""
    C = np.atleast_2d(np.asarray(C, float))
    if not np.isfinite(C).all():
        return math.inf
    if C.shape == (1, 1):
        return 0.6744897501960817 * math.sqrt(C[0, 0])
    w = np.clip(np.linalg.eigvalsh(C), 0.0, None)
    return float(np.median(np.sqrt(w[0] * _NORMALS[0] ** 2 + w[1] * _NORMALS[1] ** 2)))
