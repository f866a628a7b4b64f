"""Models from a scene: the membrane as a scene's [membrane], [target] and [chamber] sections
describe it, pressed by a rigid target (:class:`~jointsim.mechanics.dome.MembraneModel`) or a
soft one (:class:`~jointsim.mechanics.soft_target.SoftTargetModel`). Above both model
modules, so neither imports the other's factory."""

from __future__ import annotations

import numpy as np

from ..geometry import DomeSurface, chamber_cap, flat_disc
from ..scene import Scene
from .dome import MembraneModel, membrane_material
from .newton import NewtonError
from .soft_target import SoftTargetModel, soft_material

__all__ = ["membrane_from_scene"]


def membrane_from_scene(
    scene: Scene,
    target_radius: float | None = None,
    dome: DomeSurface | None = None,
    target_modulus: float | None = None,
    target_poisson: float | None = None,
    contact_slave: str | None = None,
    device: str = "cpu",
    inflate_from: np.ndarray | None = None,
    target_turn: float = 0.0,
    target_mesh_size: float | None = None,
    target_fine_radius: float | None = None,
) -> MembraneModel:
    """The membrane of ``scene`` (its [membrane] and [target] sections and chamber); the
    target's radius may be overridden by ``target_radius`` m; ``dome`` defaults to the
    scene's undeformed dome, meshed isotropically with [membrane] rim_vertices, or with
    [membrane] moulding = "flat" a flat disc inflated until its apex reaches the dome
    height (the reservoir then holds the pressure that takes; reservoir_pressure_pa is not
    used). A soft
    target ([target] kind = "soft", or any ``target_modulus`` Pa given) gives a
    :class:`~jointsim.mechanics.soft_target.SoftTargetModel` with that Young's modulus and
    ``target_poisson`` (default the scene's), and ``contact_slave`` passed on to it (None:
    its rule, the softer body's nodes). ``device``: the Warp device of the element kernels.
    ``inflate_from``: the membrane's displacement at rest in an earlier model of this scene (or
    of it with its moduli scaled), which this one's rest state is solved from: the inflation of
    a flat moulding, the reservoir head's of a cap (ignored without a head).
    ``target_turn`` (rad): a soft target's mesh turned about its axis
    (:data:`~jointsim.mechanics.soft_target.GENERIC_TURN` where derivatives are taken);
    ``target_mesh_size`` (m): a soft target's cell size where it touches (None: the model's
    default, half the membrane's median edge); ``target_fine_radius`` (m): a soft target graded
    from that size out to this far from its lowest point
    (:func:`~jointsim.mechanics.soft_target.graded_hemisphere_mesh`; None: layered)."""
    m = scene.membrane
    c = scene.chamber
    t = scene.target
    kw = {}
    cls = MembraneModel
    if target_modulus is not None or target_poisson is not None or t.kind == "soft":
        cls = SoftTargetModel
        kw["target_material"] = soft_material(
            t.youngs_modulus if target_modulus is None else target_modulus,
            t.poisson_ratio if target_poisson is None else target_poisson,
        )
        kw["contact_slave"] = contact_slave
        kw["target_turn"] = target_turn
        kw["target_mesh_size"] = target_mesh_size
        kw["target_fine_radius"] = target_fine_radius
    else:
        for name, value in (("contact_slave", contact_slave), ("target_mesh_size", target_mesh_size),
                            ("target_fine_radius", target_fine_radius)):
            if value is not None:
                raise ValueError(f"{name} = {value!r}: only for a soft target (give target_modulus)")
    flat = m.moulding == "flat"
    if dome is None:
        dome = flat_disc(c.base_radius, m.rim_vertices) if flat else chamber_cap(c, m.rim_vertices)
    if flat:
        kw["inflate_to"] = c.dome_height
    kw["inflate_from"] = inflate_from
    try:
        return _model(cls, dome, scene, target_radius, device, kw)
    except NewtonError as e:
        # the only solve of a model's construction is its state at rest under the saline
        what = (f"inflated to the dome height ({c.dome_height * 1e3:g} mm, membrane.moulding = \"flat\")" if flat
                else f"under membrane.reservoir_pressure_pa = {m.reservoir_pressure:g}")
        hint = " (a suction this strong collapses the dome)" if not flat and m.reservoir_pressure < 0 else ""
        raise NewtonError(f"the membrane has no equilibrium at rest {what}{hint}: {e}") from e


def _model(cls: type, dome: DomeSurface, scene: Scene, target_radius: float | None, device: str, kw: dict) -> MembraneModel:
    m, c, t = scene.membrane, scene.chamber, scene.target
    flat = m.moulding == "flat"
    material = membrane_material(m)
    return cls(
        dome,
        c.membrane_thickness,
        material,
        m.layers,
        0.0 if flat else m.reservoir_pressure,
        t.radius if target_radius is None else target_radius,
        friction=t.friction,
        closed=m.chamber == "closed",
        volumetric=m.volumetric,
        device=device,
        element=m.element,
        **kw,
    )
