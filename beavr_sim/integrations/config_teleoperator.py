"""``--teleop.type=beavr_quest``: the config of
:class:`beavr_sim.integrations.teleoperator.BeavrQuestTeleop`.

``source=quest``: the BEAVR Quest app's sockets (bound on ``headset_host``, the standard ports
of ``docs/formats.md``), on the wall clock. ``source=trace``: a recorded VR trace (``trace``,
or the bundled one of ``task``), by default on the ``tick`` clock: each ``get_action`` plays
1/fps of the trace, so a replay is the same however fast the caller's loop runs.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from pathlib import Path

from lerobot.teleoperators.config import TeleoperatorConfig

from beavr_sim.assets import bundled_trace
from beavr_sim.headset.webxr_server import WebXRConfig
from beavr_sim.integrations.options import check_embodiment, check_positive_int, check_task
from beavr_sim.naming import check_name
from beavr_sim.wire.ports import PortConfig, TransportConfig

#: The teleoperator type on LeRobot's command line (``--teleop.type=beavr_quest``).
TELEOP_TYPE = "beavr_quest"
SOURCES = ("quest", "trace", "webxr")
#: ``tick``: each get_action advances the source's clock by 1/fps (traces only);
#: ``real``: the wall clock.
CLOCKS = ("tick", "real")
#: The headset streams ``quest_ports`` sets, in order.
QUEST_PORTS = ("quest_right", "quest_left", "quest_resolution", "quest_pause")


@TeleoperatorConfig.register_subclass(TELEOP_TYPE)
@dataclass(kw_only=True)
class BeavrQuestTeleopConfig(TeleoperatorConfig):
    """Quest hand tracking -> joint targets of an embodiment (validated in ``__post_init__``)."""

    source: str = "quest"
    #: A VR trace (MCAP); default with ``source=trace``: the bundled trace of ``task``.
    trace: str | None = None
    #: The task: picks the bundled trace and the fixtures the arm IK keeps off (default: the
    #: trace's task, else none).
    task: str | None = None
    #: The robot it drives (default: the trace's embodiment, else xarm7_leap_right).
    embodiment: str | None = None
    #: The task layout's seed (fixture poses; default: the trace's seed, else 0).
    seed: int | None = None
    #: Actions per second the caller asks for (LeRobot's ``--fps``; the operator's control
    #: period is 1/fps).
    fps: int = 30
    #: ``tick`` or ``real`` (default: ``tick`` for traces, ``real`` for the headset).
    clock: str | None = None
    #: Play the trace again from its start when it ends (else the hands hold at its end).
    loop_trace: bool = False
    #: Interface the headset sockets bind to ("0.0.0.0": every interface).
    headset_host: str = "127.0.0.1"
    #: The app's four ports if its Network.json changed them: [right hand, left hand,
    #: resolution, pause] (default: 8087, 8110, 8095, 8100).
    quest_ports: list[int] | None = None
    #: ``source=webxr``: where the page is served (loopback unless a LAN address is given:
    #: then HTTPS with a self-signed certificate) and its port (default 8443; 0: any free).
    webxr_host: str = "127.0.0.1"
    webxr_port: int | None = None

    def webxr_config(self):
        """The WebXR page server's :class:`~beavr_sim.headset.webxr_server.WebXRConfig`."""
        if self.webxr_port is None:
            return WebXRConfig(host=self.webxr_host)
        return WebXRConfig(host=self.webxr_host, port=self.webxr_port)

    def transport(self):
        """The headset sockets' :class:`~beavr_sim.wire.ports.TransportConfig`."""
        ports = PortConfig()
        if self.quest_ports is not None:
            if len(self.quest_ports) != len(QUEST_PORTS):
                raise ValueError(
                    f"quest_ports needs {len(QUEST_PORTS)} ports ({', '.join(QUEST_PORTS)}), "
                    f"got {list(self.quest_ports)}"
                )
            ports = replace(ports, **dict(zip(QUEST_PORTS, self.quest_ports, strict=True)))
        return TransportConfig(headset_host=self.headset_host, ports=ports)

    def __post_init__(self) -> None:
        check_name("source", self.source, SOURCES)
        check_positive_int("fps", self.fps)
        if self.embodiment is not None:
            check_embodiment(self.embodiment)
        if self.task is not None:
            self.task = check_task(self.task, self.embodiment)
        if self.source == "trace":
            if self.trace is None:
                if self.task is None:
                    raise ValueError(
                        "source=trace needs a trace file (--teleop.trace=F.mcap) or a task whose "
                        "bundled trace to play (--teleop.task=PickupBox)"
                    )

                self.trace = str(bundled_trace(self.task, self.embodiment))
            if not Path(self.trace).is_file():
                raise FileNotFoundError(f"trace file not found: {self.trace}")
            self.clock = self.clock or "tick"
        else:
            if self.trace is not None:
                raise ValueError("trace needs source=trace")
            self.clock = self.clock or "real"
            if self.clock != "real":
                raise ValueError(
                    f"the headset (source={self.source}) runs on the real clock: clock=real"
                )
            if self.source == "webxr":
                self.webxr_config()  # raises on a bad host or port
            else:
                self.transport()  # raises on a bad host or ports
        check_name("clock", self.clock, CLOCKS)
