"""Hyperelastic material laws of the dome (Ecoflex 00-50) and of soft targets.

Yeoh with a volumetric penalty, in the isochoric invariant Ī₁ = J^{-2/3} tr(FᵀF):

    W(F) = C₁(Ī₁ − 3) + C₂(Ī₁ − 3)² + C₃(Ī₁ − 3)³ + κ/2 (J − 1)²

Neo-Hookean is the case C₁ = μ/2, C₂ = C₃ = 0. The first Piola–Kirchhoff stress is

    P = 2 W₁ J^{-2/3} (F − Ī₁·J^{2/3}/3 · F^{-T}) + κ (J − 1) J F^{-T},   W₁ = ∂W/∂Ī₁,

and its derivative along dF = e_j e_mᵀ (the tangent's column jm), with D = F − I₁/3 F^{-T},
T = F^{-T}, I₁ = tr FᵀF, W₂ = ∂²W/∂Ī₁², p̃ = κ(J² − J):

    ∂P/∂F_jm = (4 W₂ J^{-4/3} D_jm − 4/3 W₁ J^{-2/3} T_jm) D
             + (κ(2J − 1) J T_jm − 4/3 W₁ J^{-2/3} F_jm) T
             + (2/3 W₁ J^{-2/3} I₁ − p̃) T_{·m} ⊗ T_{j·} + 2 W₁ J^{-2/3} e_j e_mᵀ

The element stiffness wants it contracted with two nodes' shape-function gradients g_a, g_b,
K_ab = Σ_km g_a,k ∂P_·k/∂F_·m g_b,m, which takes a closed form in the nodes' vectors d = D g,
t = T g, f = F g (the coefficients c_* of :class:`Tangent`):

    K_ab = d_a ⊗ (c_dd d_b − c_dt t_b) + t_a ⊗ (c_tt t_b − c_dt f_b) + c_outer t_b ⊗ t_a + c_e (g_a·g_b) I

Defaults (DESIGN.md): neo-Hookean μ ≈ 22 kPa, or Yeoh C₁ 9.8, C₂ 0.91, C₃ −0.16 kPa (fits to
Marechal et al., Soft Robotics 2021, λ ≤ 2); κ = 1000·μ (ν ≈ 0.4995), nearly incompressible.
How the volumetric term is integrated over an element (pointwise or by mean dilatation) is the
element kernel's choice (fem.py); :func:`tangent_with_pressure` serves both.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .._warp import wp

__all__ = ["Material", "Tangent", "first_piola", "stiffness_block", "strain_energy", "tangent_with_pressure"]


@dataclass(frozen=True)
class Material:
    """Yeoh coefficients ``c1``, ``c2``, ``c3`` (Pa) and bulk modulus ``bulk`` (Pa)."""

    c1: float
    c2: float = 0.0
    c3: float = 0.0
    bulk: float = 0.0

    def __post_init__(self) -> None:
        if not self.c1 > 0:
            raise ValueError(f"c1 = {self.c1}: must be > 0 Pa (the small-strain shear modulus is 2·c1)")
        if not self.bulk > 0:
            raise ValueError(f"bulk = {self.bulk}: must be > 0 Pa")
        # W₁ = ∂W/∂Ī₁ must stay positive over the fit's range (uniaxial λ ≤ 2: Ī₁ − 3 ≤ 2)
        d = np.linspace(0, 2, 41)
        if np.any(self.c1 + 2 * self.c2 * d + 3 * self.c3 * d**2 <= 0):
            raise ValueError("Yeoh coefficients (c1, c2, c3) give a non-positive stiffness for stretches up to 2")

    @classmethod
    def neo_hookean(cls, mu: float, bulk_ratio: float = 1000.0) -> "Material":
        """Neo-Hookean with shear modulus ``mu`` (Pa) and κ = ``bulk_ratio``·μ."""
        if not mu > 0:
            raise ValueError(f"mu = {mu}: must be > 0 Pa")
        if not bulk_ratio > 0:
            raise ValueError(f"bulk_ratio = {bulk_ratio}: must be > 0")
        return cls(mu / 2, 0.0, 0.0, bulk_ratio * mu)

    @classmethod
    def yeoh(cls, c1: float, c2: float, c3: float, bulk_ratio: float = 1000.0) -> "Material":
        return cls(c1, c2, c3, bulk_ratio * 2 * c1)

    @property
    def mu(self) -> float:
        """Small-strain shear modulus 2·C₁."""
        return 2 * self.c1

    def cauchy_stress(self, F: np.ndarray) -> np.ndarray:
        """Cauchy stress σ = P Fᵀ / J (m, 3, 3) Pa at deformation gradients ``F`` (m, 3, 3), P the
        module docstring's: σ = 2 W₁ J^{-5/3} (F Fᵀ − I₁/3 I) + κ (J − 1) I. For output (the
        membrane's VTU); the solver's stress is the Warp kernels'."""
        F = np.asarray(F, float)
        J = np.linalg.det(F)
        B = F @ np.swapaxes(F, 1, 2)
        i1 = np.trace(B, axis1=1, axis2=2)
        d = J ** (-2.0 / 3.0) * i1 - 3.0
        w1 = self.c1 + 2 * self.c2 * d + 3 * self.c3 * d**2
        eye = np.eye(3)
        return ((2 * w1 * J ** (-5.0 / 3.0))[:, None, None] * (B - (i1 / 3)[:, None, None] * eye)
                + (self.bulk * (J - 1))[:, None, None] * eye)

    def uniaxial_nominal_stress(self, stretch: np.ndarray) -> np.ndarray:
        """Incompressible uniaxial nominal stress P = 2(λ − λ⁻²)·W₁(I₁), I₁ = λ² + 2/λ."""
        lam = np.asarray(stretch, float)
        d = lam**2 + 2 / lam - 3
        w1 = self.c1 + 2 * self.c2 * d + 3 * self.c3 * d**2
        return 2 * (lam - lam**-2) * w1


@wp.func
def strain_energy(F: wp.mat33d, c1: wp.float64, c2: wp.float64, c3: wp.float64, kappa: wp.float64) -> wp.float64:
    """W(F) of the Yeoh law with a volumetric penalty (see module docstring)."""
    J = wp.determinant(F)
    i1 = wp.trace(wp.transpose(F) @ F) * wp.pow(J, wp.float64(-2.0 / 3.0))
    d = i1 - wp.float64(3.0)
    return c1 * d + c2 * d * d + c3 * d * d * d + wp.float64(0.5) * kappa * (J - wp.float64(1.0)) * (J - wp.float64(1.0))


@wp.struct
class Tangent:
    """What P and the tangent ∂P/∂F share at one F (module docstring's notation)."""

    F: wp.mat33d
    T: wp.mat33d  # F^{-T}
    D: wp.mat33d  # F − I₁/3 F^{-T}
    c_dd: wp.float64  # 4 W₂ J^{-4/3}
    c_dt: wp.float64  # 4/3 W₁ J^{-2/3}
    c_tt: wp.float64  # p J + k_local J² (penalty law: κ (2J − 1) J)
    c_outer: wp.float64  # 2/3 W₁ J^{-2/3} I₁ − p J
    c_e: wp.float64  # 2 W₁ J^{-2/3}
    c_vol: wp.float64  # p J


@wp.func
def tangent_with_pressure(F: wp.mat33d, c1: wp.float64, c2: wp.float64, c3: wp.float64, p: wp.float64, k_local: wp.float64) -> Tangent:
    """The invariants and coefficients at F that the stress and the tangent are built from, with
    the volumetric stress p·J·F^{-T} for a given pressure p and the volumetric stiffness
    k_local·J²·F^{-T}⊗F^{-T} of a pointwise U(J): p = κ(J − 1), k_local = κ for the penalty law
    (the module docstring's P and ∂P/∂F); k_local = 0 where p is an element's constant
    pressure, whose stiffness is added per element (the mean-dilatation form in fem.py)."""
    t = Tangent()
    J = wp.determinant(F)
    T = wp.transpose(wp.inverse(F))
    jm23 = wp.pow(J, wp.float64(-2.0 / 3.0))
    I1 = wp.trace(wp.transpose(F) @ F)
    d = I1 * jm23 - wp.float64(3.0)
    w1 = c1 + wp.float64(2.0) * c2 * d + wp.float64(3.0) * c3 * d * d
    w2 = wp.float64(2.0) * c2 + wp.float64(6.0) * c3 * d
    t.F = F
    t.T = T
    t.D = F - I1 / wp.float64(3.0) * T
    t.c_dd = wp.float64(4.0) * w2 * jm23 * jm23
    t.c_dt = wp.float64(4.0 / 3.0) * w1 * jm23
    t.c_tt = p * J + k_local * J * J
    t.c_outer = wp.float64(2.0 / 3.0) * w1 * jm23 * I1 - p * J
    t.c_e = wp.float64(2.0) * w1 * jm23
    t.c_vol = p * J
    return t


@wp.func
def stiffness_block(t: Tangent, w: wp.float64, da: wp.vec3d, ta: wp.vec3d, ga: wp.vec3d, tb: wp.vec3d, pb: wp.vec3d, rb: wp.vec3d,
                    gb: wp.vec3d) -> wp.mat33d:
    """K_ab at one quadrature point of weight w (the module docstring's closed form), from node a's
    d_a = D g_a, t_a = T g_a, g_a and node b's t_b, p_b = c_dd d_b − c_dt t_b, r_b = c_tt t_b − c_dt F g_b, g_b."""
    block = w * (wp.outer(da, pb) + wp.outer(ta, rb) + t.c_outer * wp.outer(tb, ta))
    shear = w * t.c_e * wp.dot(ga, gb)
    for i in range(3):
        block[i, i] = block[i, i] + shear
    return block


@wp.func
def first_piola(t: Tangent) -> wp.mat33d:
    """P = ∂W/∂F = 2 W₁ J^{-2/3} D + κ (J − 1) J F^{-T} (module docstring)."""
    return t.c_e * t.D + t.c_vol * t.T
