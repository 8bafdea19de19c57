"""Our own MuJoCo-style rigid-body dynamics in NumPy (issue 7).

``types`` (the frozen :class:`Model`, :class:`State`, :class:`Options`, :class:`Body`), ``io`` (building and
validating them), ``collide`` (contacts against planes, the
room distance field and other bodies), ``solve`` (soft contacts, Coulomb friction), ``integrate``
(semi-implicit, quaternions), ``ccd`` (no tunnelling through the room), ``sleep``, ``step`` and
``drop`` (a whole drop of objects into a room).
"""

from pipeline.physics.io import box_body, build_model, make_state, model_poses, sphere_body
from pipeline.physics.step import penetration, step
from pipeline.physics.types import Body, Model, Options, State

__all__ = ["Body", "Model", "Options", "State", "box_body", "build_model", "make_state", "model_poses",
           "penetration", "sphere_body", "step"]
