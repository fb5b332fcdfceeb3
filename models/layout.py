"""Which coordinates exist follows from the scene's effects; this is the one place that says how.

Generalized coordinates  x = (s_p if `reel`, q_2 ... q_{N+1})            size nx = [1] + 3N
Generalized velocities   w = (ṡ_p if `reel`, q̇_2 ... q̇_{N+1}, Ω if `rigid_body`)   size nw
ODE state (baselines)    y = (x, quat if `rigid_body`, w, W if non-conservative forces)

W is the accumulated work of the non-conservative forces (Carnot loss, reel control, axial
damping); it is carried in the ODE state so that E - W can be checked to the integrator's own
accuracy. Each effect declares what it adds (`models.effects.Effect.state`, `.forcing`).
"""

from __future__ import annotations

from dataclasses import dataclass

from reelbench.models.effects import get_effect


@dataclass(frozen=True)
class StateLayout:
    elements: int
    has_reel: bool
    has_attitude: bool
    has_work: bool
    #: π3 is conserved by the physics (every listed effect's `Effect.conserves_pi3`)
    conserves_pi3: bool = True

    @classmethod
    def from_scene(cls, scene) -> "StateLayout":
        listed = [get_effect(e) for e in scene.effects]
        state = {c for e in listed for c in e.state}
        return cls(
            elements=scene.string.elements,
            has_reel="s_p" in state,
            has_attitude="attitude" in state,
            has_work=any(e.forcing for e in listed),
            conserves_pi3=all(e.conserves_pi3 for e in listed),
        )

    # generalized coordinates / velocities -------------------------------------------
    @property
    def n_reel(self) -> int:
        return 1 if self.has_reel else 0

    @property
    def nx(self) -> int:
        return self.n_reel + 3 * self.elements

    @property
    def nw(self) -> int:
        return self.nx + (3 if self.has_attitude else 0)

    @property
    def nodes(self) -> slice:
        """Slice of x (and of w) holding q_2 ... q_{N+1} (flattened, node-major)."""
        return slice(self.n_reel, self.nx)

    @property
    def omega(self) -> slice:
        """Slice of w holding Ω (empty without a rigid body)."""
        return slice(self.nx, self.nw)

    # ODE state -------------------------------------------------------------------------
    @property
    def n_quat(self) -> int:
        return 4 if self.has_attitude else 0

    @property
    def y_x(self) -> slice:
        return slice(0, self.nx)

    @property
    def y_quat(self) -> slice:
        return slice(self.nx, self.nx + self.n_quat)

    @property
    def y_w(self) -> slice:
        start = self.nx + self.n_quat
        return slice(start, start + self.nw)

    @property
    def y_work(self) -> slice:
        start = self.nx + self.n_quat + self.nw
        return slice(start, start + (1 if self.has_work else 0))

    @property
    def ny(self) -> int:
        return self.y_work.stop
