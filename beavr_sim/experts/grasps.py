"""Grasp geometry of the LEAP hand for the scripted experts: hand poses and finger shapes.

The experts use one grasp, a *front pinch*: palm facing down, fingers pointing forward and
slightly curled, the object held below the fingers between the three fingertips (far side)
and the thumb tip (near side). Its numbers were measured in the twin (hand frame: +z along
the fingers, +x out of the palm, origin on the adapter face; the thumb at +y on the right
hand, mirrored on the left):

- ``PINCH_CENTRE_IN_HAND``: where the centre of a 5-7 cm object sits in the hand frame when
  the fingers close on it (sideways: midway between the thumb tip and the middle of the
  three fingertips, on both hands). The fingertips reach about 2 cm below (palm-normal) this point, so
  the centre must stay >= ``MIN_PINCH_HEIGHT`` above the table.
- Finger joint targets: open (pre-shape) and closed; the closed shape pushes past the object
  surface so the position servos squeeze it.
"""

from __future__ import annotations

import numpy as np

from beavr_sim.experts.ik import rotation_from_axes, se3

PINCH_CENTRE_IN_HAND = np.array([0.09, -0.013, 0.12])
#: Lowest height of the pinch centre above the table top (fingertips clear the table).
MIN_PINCH_HEIGHT = 0.03

# Hand joint order per finger: index, middle, ring (each: spread, MCP, PIP, DIP), thumb (4).
_FINGER_MCP = [1, 5, 9]
_FINGER_PIP = [2, 6, 10]
_FINGER_DIP = [3, 7, 11]
_THUMB = slice(12, 16)


def finger_shape(mcp: float, pip: float, dip: float, thumb) -> np.ndarray:
    """16 hand joint targets: the three fingers alike, the thumb's four joints given."""
    q = np.zeros(16)
    q[_FINGER_MCP], q[_FINGER_PIP], q[_FINGER_DIP] = mcp, pip, dip
    q[_THUMB] = thumb
    return q


#: Fingers slightly curled, thumb swung under the palm and away from the fingers.
PINCH_OPEN = finger_shape(0.3, 0.3, 0.0, (1.6, 0.4, 1.0, -1.0))
#: Fingers and thumb closed on an object 5-7 cm across.
PINCH_CLOSED = finger_shape(0.8, 0.8, 0.4, (1.6, 0.4, 1.0, 0.5))
#: Fingers open flat and thumb out, to let go of an object.
RELEASE = finger_shape(0.0, 0.0, 0.0, (1.6, 0.4, 1.0, -1.0))


def R_world_palm_down(heading: float) -> np.ndarray:
    """Palm facing down, fingers horizontal along world heading ``heading`` (rad about +z)."""
    return rotation_from_axes([np.cos(heading), np.sin(heading), 0.0], [0.0, 0.0, -1.0])


def T_world_hand_pinching(centre_world, R_world_hand: np.ndarray, centre_in_hand=None):
    """The hand pose that puts the pinch centre (or ``centre_in_hand``, e.g. where a held
    object really sits in the hand) at ``centre_world`` with orientation ``R``."""
    p_hand = PINCH_CENTRE_IN_HAND if centre_in_hand is None else np.asarray(centre_in_hand)
    return se3(R_world_hand, np.asarray(centre_world, float) - R_world_hand @ p_hand)


def fold_heading(yaw: float, period: float = np.pi / 2, reference: float = 0.0) -> float:
    """The heading equivalent to ``yaw`` modulo ``period`` (an object's symmetry) nearest
    ``reference``: a square box can be pinched across any pair of opposite faces."""
    return reference + (yaw - reference + period / 2) % period - period / 2
