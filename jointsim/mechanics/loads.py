"""The membrane's energy terms: what acts on a :class:`~jointsim.mechanics.body.MembraneBody`.

Owns which terms make up the membrane's energy and how each is set up from the body: the
hyperelastic strain energy (wedge or P2 element kernel, on the Warp device), the saline
pressure on the inner surface, the penalty contact of a rigid sphere on the outer surface and,
where the scene gives a coefficient, Coulomb friction there. A new term is a new field here and
an entry in :attr:`MembraneTerms.all`; the solver (:mod:`.dome`) minimises whatever they sum to.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .body import MembraneBody
from .contact import SphereContact, SphereFriction, nodal_areas
from .fem import ElasticTerm
from .materials import Material
from .pressure import PressureTerm, linear_subtriangles
from .wedge import WedgeElasticTerm

__all__ = ["MembraneTerms", "membrane_terms"]


@dataclass(frozen=True, eq=False)
class MembraneTerms:
    """The energy terms of one membrane: ``elastic``, the saline ``pressure``, the target's
    ``contact`` and its ``friction`` (None when frictionless)."""

    elastic: object
    pressure: PressureTerm
    contact: SphereContact
    friction: SphereFriction | None

    @property
    def all(self) -> list:
        return [self.elastic, self.pressure, self.contact] + ([self.friction] if self.friction else [])


def membrane_terms(body: MembraneBody, material: Material, *, pressure: float = 0.0, target_radius: float = 7.5e-3,
                   penalty: float | None = None, friction: float = 0.0, volumetric: str = "pointwise",
                   device: str = "cpu") -> MembraneTerms:
    """The terms on ``body``: ``material``'s strain energy (``volumetric`` form for P2
    tetrahedra; wedges project their own), saline at ``pressure`` Pa, a rigid sphere of
    ``target_radius`` m parked far away, its penalty stiffness ``penalty`` N/m³ (default 100 ×
    the layer's 3μ/h), Coulomb ``friction``. ``device``: where Warp runs the element kernel
    ("cpu", or "cuda:0" where a GPU is); contact, pressure and the sparse solves stay on the host."""
    if body.element == "wedge15":
        if volumetric != "pointwise":
            raise ValueError(f"volumetric = {volumetric!r}: the wedge15 element has its own (projected) volumetric form; "
                             "volumetric applies to element = 'p2_tet' only")
        elastic = WedgeElasticTerm(body.mesh, material, device=device)
    else:
        elastic = ElasticTerm(body.mesh, material, volumetric=volumetric, device=device)
    X = body.mesh.nodes
    pressure_term = PressureTerm(X, body.inner_tris, pressure, sign=-1.0)
    nodes, w = nodal_areas(X, linear_subtriangles(body.outer_faces))
    h = body.thickness / body.layers
    k = penalty if penalty is not None else 100 * 3 * material.mu / h
    # the contact Hessian's curvature term is exact up to 1 % of a layer's thickness of
    # penetration (equilibria sit at 1–2 µm: quadratic convergence there) and capped beyond,
    # where trial states 0.5 mm deep would make it strongly indefinite (measured, 64-rim
    # membrane to 3 mm: 45 factorisations against 50 uncapped-out and 52 exact)
    contact = SphereContact(X, nodes, w, target_radius, k, curvature_cap=0.01 * h)
    contact.centre = np.array([0.0, 0.0, 1e3])  # far away until pressed
    fric = SphereFriction(contact, friction, slip=1e-3 * h) if friction > 0 else None
    return MembraneTerms(elastic, pressure_term, contact, fric)
