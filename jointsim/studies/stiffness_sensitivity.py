"""Stiffness identifiability: how far a target's Young's modulus moves what the sensor measures
(contact force, displaced saline volume, contact area) at a given stage depth, against how far
the membrane's own modulus moves them. The physics limit of force-based elastography with
this sensor, whatever the estimator.

For a press to stage depth d, with the log-sensitivities S_E = ∂ln F/∂ln E (target) and
S_μ = ∂ln F/∂ln μ (membrane), a force known to a relative ε_F and a membrane modulus known to
a relative ε_μ give the target's modulus to, at first order,

    δ ln E = √(ε_F² + (S_μ ε_μ)²) / |S_E|.

Measuring the displaced volume V as well (the EIT signal's source) gives two equations for
the two unknowns ln E and ln μ: with J = [[S_E^F, S_μ^F], [S_E^V, S_μ^V]] and relative errors
ε_F, ε_V, the error of ln E is the first row of J⁻¹ applied to them (:func:`joint_modulus_error`),
and the membrane's modulus need not be known.

S_E comes from presses at log-spaced moduli (central differences in ln E); S_μ from the same
press with the membrane's moduli scaled by ``MEMBRANE_STEP`` (one-sided difference).

The soft-target contact is node-to-surface with the softer body's nodes as slaves, so the
slave side flips where the target's shear modulus passes 10× the membrane's. The two choices
differ by a discretisation error that can exceed the modulus signal; S_E is therefore taken
only between moduli with the same slave side, and the press at the first modulus past the
flip is repeated with the other side (``crosscheck``) to measure that error.
"""

from __future__ import annotations

import concurrent.futures as cf
import csv
import json
import math
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Callable

import numpy as np

from ..io.export import atomic_path
from ..io.figures import pyplot

__all__ = ["PressCurve", "StudyResult", "press_curve", "run_study", "modulus_error", "joint_modulus_error", "write_report", "MEMBRANE_STEP"]

MEMBRANE_STEP = 1.1  # the membrane moduli's scale for S_μ
DEFAULT_MODULI_KPA = (10.0, 30.0, 100.0, 300.0, 1000.0, 3000.0)
DEFAULT_DEPTHS_MM = (0.5, 1.0, 1.5, 2.0, 2.5, 3.0)
# (ε_F, ε_μ) of the error table: an ideal force, a 1 % load cell with the membrane calibrated
# per unit to 5 %, and the datasets' ×0.5–2 log-uniform randomisation (SD of ln: 2 ln 2 / √12)
ERROR_CASES = ((0.01, 0.0), (0.01, 0.05), (0.01, 2 * math.log(2) / math.sqrt(12)))
JOINT_PRECISION = 0.01  # relative error of force and of displaced volume, for the joint estimate


@dataclass(frozen=True)
class PressCurve:
    """One on-axis press: target ``modulus`` Pa (inf: rigid), membrane moduli × ``membrane_scale``,
    the contact's ``slave`` side ("target", "membrane"; "rigid" for a rigid target); per stage
    ``depths`` (m): |force| N, ``displaced_volume`` m³, ``contact_area`` m²."""

    modulus: float
    membrane_scale: float
    slave: str
    depths: np.ndarray
    force: np.ndarray
    displaced_volume: np.ndarray
    contact_area: np.ndarray


def press_curve(scene, radius: float, modulus: float, depths: np.ndarray, membrane_scale: float = 1.0,
                slave: str | None = None) -> PressCurve:
    """Press a sphere of ``radius`` m and Young's ``modulus`` Pa (``math.inf``: rigid) on the
    dome's axis to each stage depth of ``depths`` (m, increasing, past first contact);
    ``slave``: the soft contact's slave side (None: the model's rule)."""
    from ..mechanics.build import membrane_from_scene

    if not radius > 0:
        raise ValueError(f"radius = {radius}: must be > 0 m")
    if not modulus > 0:
        raise ValueError(f"modulus = {modulus}: must be > 0 Pa (math.inf for a rigid target)")
    if not membrane_scale > 0:
        raise ValueError(f"membrane_scale = {membrane_scale}: must be > 0")
    depths = np.asarray(depths, float)
    if depths.ndim != 1 or len(depths) == 0 or np.any(depths <= 0) or np.any(np.diff(depths) <= 0):
        raise ValueError("depths: a non-empty increasing sequence of positive stage depths (m)")
    scaled = replace(scene, membrane=scene.membrane.scaled(membrane_scale), target=replace(scene.target, kind="rigid"))
    soft = not math.isinf(modulus)
    model = membrane_from_scene(scaled, target_radius=radius, target_modulus=modulus if soft else None,
                                     contact_slave=slave if soft else None)
    top = model.first_contact_height((0.0, 0.0))
    states = [model.press(np.array([0.0, 0.0, top - d])) for d in depths]
    return PressCurve(modulus, membrane_scale, model.contact.slave if soft else "rigid", depths, np.array([np.linalg.norm(s.force) for s in states]),
                      np.array([s.displaced_volume for s in states]), np.array([s.contact_area for s in states]))


@dataclass(frozen=True)
class StudyResult:
    """``curves[k]`` at ``moduli[k]`` (Pa, increasing, the last inf: rigid) and ``membrane[k]`` the
    same press with the membrane stiffened by ``MEMBRANE_STEP``; ``radius`` m; ``crosscheck``:
    the first press past the slave flip with the other slave side (None without a flip)."""

    radius: float
    moduli: np.ndarray
    curves: list[PressCurve]
    membrane: list[PressCurve]
    crosscheck: PressCurve | None = None

    @property
    def depths(self) -> np.ndarray:
        return self.curves[0].depths

    def quantity(self, name: str, membrane: bool = False) -> np.ndarray:
        """(moduli, depths) array of ``name`` (force, displaced_volume or contact_area)."""
        return np.array([getattr(c, name) for c in (self.membrane if membrane else self.curves)])

    def target_sensitivity(self, name: str = "force") -> np.ndarray:
        """S_E = ∂ln q/∂ln E (moduli, depths): central differences over the soft moduli with the
        same slave side (one-sided at the ends of each run); 0 for the rigid row, NaN for a
        modulus alone on its side."""
        q = np.log(self.quantity(name))
        s = np.zeros_like(q)
        slaves = [c.slave for c in self.curves]
        for side in ("target", "membrane"):
            k = np.array([i for i, x in enumerate(slaves) if x == side], int)
            if len(k) == 1:
                s[k] = np.nan
            elif len(k) >= 2:
                s[k] = np.gradient(q[k], np.log(self.moduli[k]), axis=0)
        return s

    def membrane_sensitivity(self, name: str = "force") -> np.ndarray:
        """S_μ = ∂ln q/∂ln μ (moduli, depths), one-sided over ×MEMBRANE_STEP."""
        return (np.log(self.quantity(name, True)) - np.log(self.quantity(name))) / math.log(MEMBRANE_STEP)


def modulus_error(s_target: np.ndarray, s_membrane: np.ndarray, force_precision: float, membrane_uncertainty: float) -> np.ndarray:
    """Relative 1-σ error of the target modulus, exp(δ ln E) − 1, with δ ln E from the module
    docstring; inf where the measurement does not depend on the modulus."""
    if not force_precision >= 0 or not membrane_uncertainty >= 0:
        raise ValueError("force_precision and membrane_uncertainty: relative 1-sigma errors, must be >= 0")
    num = np.sqrt(force_precision**2 + (np.asarray(s_membrane) * membrane_uncertainty) ** 2)
    with np.errstate(divide="ignore", over="ignore"):
        return np.expm1(num / np.abs(np.asarray(s_target)))


def joint_modulus_error(s_force: tuple, s_volume: tuple, force_precision: float, volume_precision: float) -> np.ndarray:
    """Relative 1-σ error of the target modulus from force and displaced volume together, the
    membrane modulus unknown: ``s_force`` = (S_E, S_μ) of the force, ``s_volume`` of the volume
    (arrays broadcast); inf where the two measurements do not separate E from μ."""
    if not force_precision >= 0 or not volume_precision >= 0:
        raise ValueError("force_precision and volume_precision: relative 1-sigma errors, must be >= 0")
    (ef, mf), (ev, mv) = (np.asarray(x, float) for x in s_force), (np.asarray(x, float) for x in s_volume)
    det = ef * mv - mf * ev
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
        # first row of J⁻¹ = [S_μ^V, −S_μ^F] / det
        d = np.hypot(mv * force_precision, mf * volume_precision) / np.abs(det)
        return np.where(det == 0, np.inf, np.expm1(d))


def run_study(scene, radius: float = 7.5e-3, moduli_kpa=DEFAULT_MODULI_KPA, depths_mm=DEFAULT_DEPTHS_MM,
              workers: int = 1, progress: Callable[[int, int], None] | None = None) -> StudyResult:
    """Every modulus of ``moduli_kpa`` plus a rigid target, each also with the membrane
    stiffened, and the slave-side cross-check: 2 × (len(moduli) + 1) + 1 presses on
    ``workers`` processes; ``progress(done, total)`` after each."""
    moduli = np.array(sorted(float(e) * 1e3 for e in moduli_kpa) + [math.inf])
    if np.any(moduli[:-1] <= 0):
        raise ValueError("moduli_kpa: target moduli must be > 0 kPa")
    if workers < 1:
        raise ValueError(f"workers = {workers}: must be >= 1")
    depths = np.asarray(depths_mm, float) * 1e-3
    jobs = [(scene, radius, e, depths, s) for s in (1.0, MEMBRANE_STEP) for e in moduli]
    from ..mechanics.dome import membrane_material
    from ..mechanics.soft_target import default_contact_slave, soft_material

    membrane = membrane_material(scene.membrane)
    sides = [default_contact_slave(soft_material(e, scene.target.poisson_ratio), membrane) for e in moduli[:-1]]
    if len(set(sides)) == 2:
        first = sides.index("membrane")
        jobs.append((scene, radius, moduli[first], depths, 1.0, "target"))
    if workers == 1:
        out = []
        for j in jobs:
            out.append(press_curve(*j))
            if progress:
                progress(len(out), len(jobs))
    else:
        import multiprocessing

        with cf.ProcessPoolExecutor(workers, mp_context=multiprocessing.get_context("spawn")) as pool:
            futures = [pool.submit(press_curve, *j) for j in jobs]
            for done, f in enumerate(cf.as_completed(futures), 1):
                f.result()
                if progress:
                    progress(done, len(jobs))
            out = [f.result() for f in futures]
    n = len(moduli)
    return StudyResult(radius, moduli, out[:n], out[n : 2 * n], out[2 * n] if len(out) > 2 * n else None)


def _label(e: float) -> str:
    return "rigid" if math.isinf(e) else f"{e / 1e3:g} kPa"


def write_report(result: StudyResult, out: Path, command: str) -> list[Path]:
    """``stiffness_sensitivity.{csv,json,md,png}`` in ``out``, each written to a temporary name
    and renamed (:func:`~jointsim.io.export.atomic_path`)."""
    plt = pyplot()

    out.mkdir(parents=True, exist_ok=True)
    d_mm = result.depths * 1e3
    F = result.quantity("force")
    V = result.quantity("displaced_volume")
    A = result.quantity("contact_area")
    sF, sV = result.target_sensitivity("force"), result.target_sensitivity("displaced_volume")
    mF, mV = result.membrane_sensitivity("force"), result.membrane_sensitivity("displaced_volume")
    rigid = F[-1]
    rows = []
    for k, e in enumerate(result.moduli):
        for i, d in enumerate(d_mm):
            row = {"modulus_kpa": e / 1e3, "contact_slave": result.curves[k].slave, "depth_mm": d, "force_mN": F[k, i] * 1e3, "force_rel_rigid": F[k, i] / rigid[i],
                   "displaced_mm3": V[k, i] * 1e9, "contact_area_mm2": A[k, i] * 1e6,
                   "S_E_force": sF[k, i], "S_mu_force": mF[k, i], "S_E_volume": sV[k, i], "S_mu_volume": mV[k, i]}
            for ef, em in ERROR_CASES:
                row[f"modulus_error_F{ef:g}_mu{em:.2f}"] = float(modulus_error(sF[k, i], mF[k, i], ef, em))
            row[f"modulus_error_F_and_V{JOINT_PRECISION:g}"] = float(joint_modulus_error((sF[k, i], mF[k, i]), (sV[k, i], mV[k, i]),
                                                                                          JOINT_PRECISION, JOINT_PRECISION))
            rows.append(row)
    written = []

    def put(name: str, write) -> None:
        with atomic_path(out / name) as tmp:
            write(tmp)
        written.append(out / name)

    def write_csv(p: Path) -> None:
        with open(p, "w", newline="") as f:
            w = csv.DictWriter(f, fieldnames=list(rows[0]))
            w.writeheader()
            w.writerows(rows)

    put("stiffness_sensitivity.csv", write_csv)
    put("stiffness_sensitivity.json", lambda p: p.write_text(json.dumps({"command": command, "radius_m": result.radius,
                                                                          "membrane_step": MEMBRANE_STEP, "rows": rows}, indent=1)))
    # the table at the deepest and a middle depth: where the modulus is best and typically resolved
    picks = sorted({0, len(d_mm) // 2, len(d_mm) - 1})
    lines = ["# Stiffness identifiability on the paper's sensor", "", f"Command: `{command}`  ",
             f"On-axis presses of a sphere of radius {result.radius * 1e3:g} mm (neo-Hookean, the scene's Poisson ratio) to stage depths "
             f"{', '.join(f'{x:g}' for x in d_mm)} mm past first contact; the membrane at the scene's moduli and ×{MEMBRANE_STEP:g}.",
             "S_E = ∂ln F/∂ln E (target modulus), S_μ = ∂ln F/∂ln μ (membrane modulus). Modulus error (1 σ, first order): "
             "exp(√(ε_F² + (S_μ ε_μ)²)/|S_E|) − 1 for a force precision ε_F and a membrane-modulus uncertainty ε_μ "
             f"(ε_μ = {ERROR_CASES[-1][1]:.2f} is the datasets' ×0.5–2 log-uniform randomisation). The last column uses the "
             "displaced volume V too (the source of the EIT signal): force and volume together determine E and μ, so the "
             "membrane's modulus need not be known (error from the inverse of the 2 × 2 sensitivity matrix).", ""]
    for i in picks:
        head = "| target | contact slaves | F mN | F / rigid | displaced mm³ | S_E (force) | S_μ (force) | S_E (volume) | " + " | ".join(
            f"E error, ε_F {ef:.0%}, ε_μ {em:.0%}" for ef, em in ERROR_CASES) + f" | E error, F and V at {JOINT_PRECISION:.0%}, μ unknown |"
        lines += [f"## Stage depth {d_mm[i]:g} mm", "", head, "|" + "---|" * (9 + len(ERROR_CASES))]
        for k, e in enumerate(result.moduli):
            errs = " | ".join("—" if math.isinf(e) else _fmt_err(float(modulus_error(sF[k, i], mF[k, i], ef, em))) for ef, em in ERROR_CASES)
            joint = float(joint_modulus_error((sF[k, i], mF[k, i]), (sV[k, i], mV[k, i]), JOINT_PRECISION, JOINT_PRECISION))
            errs += " | " + ("—" if math.isinf(e) else _fmt_err(joint))
            lines.append(f"| {_label(e)} | {result.curves[k].slave} | {F[k, i] * 1e3:.2f} | {F[k, i] / rigid[i]:.3f} | {V[k, i] * 1e9:.1f} | {sF[k, i]:.3f} | "
                         f"{mF[k, i]:.3f} | {sV[k, i]:.3f} | {errs} |")
        lines.append("")
    x = result.crosscheck
    if x is not None:
        k = int(np.flatnonzero(result.moduli == x.modulus)[0])
        diff = ", ".join(f"{100 * (x.force[i] / F[k, i] - 1):+.1f} % at {d:g} mm" for i, d in enumerate(d_mm))
        lines += ["## Contact discretisation", "",
                  f"The {_label(x.modulus)} press with the {x.slave}'s nodes as slaves instead of the {result.curves[k].slave}'s: "
                  f"force {diff}. Force differences between moduli smaller than this are not resolved by the simulator.", ""]
    put("stiffness_sensitivity.md", lambda p: p.write_text("\n".join(lines) + "\n"))

    def write_png(p: Path) -> None:
        fig, ax = plt.subplots(1, 3, figsize=(14, 4.2))
        soft = np.isfinite(result.moduli)
        for i in picks:
            ax[0].semilogx(result.moduli[soft] / 1e3, F[soft, i] / rigid[i], "o-", label=f"d = {d_mm[i]:g} mm")
            ax[1].semilogx(result.moduli[soft] / 1e3, sF[soft, i], "o-", label=f"S_E, d = {d_mm[i]:g} mm")
            ax[1].semilogx(result.moduli[soft] / 1e3, mF[soft, i], "s--", label=f"S_μ, d = {d_mm[i]:g} mm")
            for ef, em in ERROR_CASES:
                err = modulus_error(sF[soft, i], mF[soft, i], ef, em)
                ax[2].loglog(result.moduli[soft] / 1e3, np.minimum(err, 1e3), "o-", label=f"d {d_mm[i]:g} mm, ε_F {ef:.0%}, ε_μ {em:.0%}")
        ax[0].set(xlabel="target modulus E (kPa)", ylabel="force / force with a rigid target", title="Force against target modulus")
        ax[1].set(xlabel="target modulus E (kPa)", ylabel="log-sensitivity of the force", title="Target (S_E) and membrane (S_μ)")
        ax[2].axhline(0.2, color="k", lw=0.8, ls=":")
        ax[2].set(xlabel="target modulus E (kPa)", ylabel="relative modulus error (1 σ)", title="Modulus error; dotted: the 20 % goal")
        for a in ax:
            a.grid(True, which="both", alpha=0.3)
            a.legend(fontsize=7)
        fig.tight_layout()
        fig.savefig(p, dpi=120, format="png")
        plt.close(fig)

    put("stiffness_sensitivity.png", write_png)
    return written


def _fmt_err(x: float) -> str:
    if math.isnan(x):
        return "n/a"  # no sensitivity: a modulus alone on its contact side
    return "> 1000 %" if x >= 10 else f"{100 * x:.0f} %"
