"""The latency harness (issue 20) runs configuration 1 briefly and reports every field."""

from __future__ import annotations

import json
import math

from beavr_sim.bench.__main__ import main
from beavr_sim.bench.latency import finite_positive


def test_latency_harness_config_1_reports_every_field(capsys, tmp_path):
    assert main(["latency", "--config", "1", "--seconds", "1.5", "--plot", str(tmp_path)]) == 0
    out, err = capsys.readouterr()
    result = json.loads(out.strip().splitlines()[-1])
    assert "send->twin" in err  # the table
    assert result["processes_died"] == [], result["exits"]
    frames = result["frames"]
    assert 0 < frames["received"]["right"] <= frames["sent"]["right"]
    assert frames["rejected"] == 0, frames
    eff = result["effectors"]["right"]
    assert eff["command_hz"] > 0 and eff["pct_of_target"] > 0
    assert math.isfinite(eff["jitter_ms"]["std_ms"])
    for key in ("latency_twin_ms", "send_to_detector_ms", "detector_to_twin_ms"):
        assert finite_positive(eff[key]), (key, eff[key])
    assert eff["latency_twin_ms"]["p50"] <= eff["latency_twin_ms"]["p99"]
    assert set(result["devices"]) == {"right_arm", "right_hand"}
    for dev in result["devices"].values():
        assert dev["write_hz"] > 0 and finite_positive(dev["latency_driver_ms"]), dev
    floor = result["floor"]
    assert floor["received"] == floor["sent"] > 0 and finite_positive(floor["latency_ms"])
    assert eff["over_floor"]["p50"] > 1
    assert {p.rsplit("/", 1)[-1] for p in result["plots"]} == {
        "latency_send_to_twin.png",
        "latency_send_to_driver.png",
    }
