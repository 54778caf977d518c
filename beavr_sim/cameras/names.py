"""What a recording calls a twin camera that has a real camera of its name.

One recording (teleop ``--record``, the ``beavr_sim`` LeRobot robot) may hold a real camera
and a twin camera of the same name, e.g. the rig's real ``front`` and the twin's ``front``
standing at its pose (``--camera-poses``). The real camera keeps the plain name
(``observation.images.front``: what a policy trained on real data reads, on the real robot
too); the twin's is ``NAME_twin`` (``observation.images.front_twin``, its depth
``front_twin_depth``). A twin camera without a real namesake keeps its name, so a sim
dataset's ``front`` and a rig dataset's real ``front`` are the same feature. Light: no LeRobot
import. Errors are one-line ``CameraSpecError``s naming the camera.
"""

from __future__ import annotations

from collections.abc import Iterable

from beavr_sim.cameras.errors import CameraSpecError

#: Appended to a twin camera's name where a real camera has that name.
TWIN_SUFFIX = "_twin"


def recorded_twin_names(twin: Iterable[str], real: Iterable[str]) -> dict[str, str]:
    """Each twin camera -> the name it is recorded under: its own, or ``NAME_twin`` where a
    real camera (or a real camera's feature, ``NAME_depth``) is ``NAME``. A ``NAME_twin``
    that is itself another camera's name is refused, naming both."""
    real_names = set(real)
    twin_names = tuple(dict.fromkeys(twin))
    recorded = {c: c + TWIN_SUFFIX if c in real_names else c for c in twin_names}
    taken = real_names | set(twin_names)
    for camera, name in recorded.items():
        if name != camera and name in taken:
            raise CameraSpecError(
                f"twin camera {camera!r} is recorded as {name!r} (a real camera is "
                f"{camera!r}), but {name!r} is also a camera; rename that camera"
            )
    return recorded
