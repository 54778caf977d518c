"""The twin's meshes on the WebXR page: each distinct mesh of the compiled model sent once in the
``scene`` message (quantised vertices, faces), with the counts of the model's mesh, decoding to
the model's vertices where the geom is in the world; the page's decoder (``twin_gl.js``, run
with node) reads the same vertices and triangles and refuses a damaged payload, saying why.
Under ``--multiprocess`` the scene and poses the twin process sends reach the page as one
process sends them."""

from __future__ import annotations

import base64
import json
import shutil
import subprocess
from pathlib import Path

import gymnasium as gym
import mujoco
import numpy as np
import pytest

import beavr_sim  # noqa: F401
from beavr_sim.headset.webxr_scene import QUANT, TwinGeometry, decode_mesh, encode_mesh
from beavr_sim.headset.webxr_server import STATIC_DIR, encode_page_message

#: Poses are sent to 1e-4 (position and rotation entries), vertices to 1/65534 of the box.
WORLD_TOLERANCE_M = 5e-4


@pytest.fixture(scope="module", params=["xarm7_leap_right", "xarm7_leap_bimanual"])
def scene(request):
    env = gym.make("beavr_sim/Pour-v0", embodiment=request.param).unwrapped
    env.reset(seed=0)
    home = env.agent_pos
    env.step(home + np.random.default_rng(0).normal(0, 0.1, home.shape).astype(np.float32))
    mujoco.mj_kinematics(env.model, env.data)  # body poses at the positions after the step
    # The page draws the render model (visual meshes) at the physics model's body poses:
    # checked below against MuJoCo's own geom poses in the render model's data.
    geometry = TwinGeometry.from_model(env.render_model)
    message = json.loads(encode_page_message(geometry.scene_message(env.data, task="Pour")))
    yield env.render_model, env.render_data(), geometry, message
    env.close()


def _mesh_geoms(model: mujoco.MjModel) -> set[int]:
    return {
        g
        for g in range(model.ngeom)
        if model.geom_type[g] == mujoco.mjtGeom.mjGEOM_MESH and model.geom_group[g] <= 2
    }


def test_every_mesh_geom_is_a_mesh_shape_with_its_entry(scene):
    model, _, geometry, message = scene
    n = len(geometry.geom_ids)
    assert _mesh_geoms(model) and _mesh_geoms(model) <= set(geometry.geom_ids.tolist())
    assert len(message["mesh"]) == len(message["shapes"]) == n
    for g, shape, k in zip(geometry.geom_ids, message["shapes"], message["mesh"], strict=True):
        is_mesh = model.geom_type[g] == mujoco.mjtGeom.mjGEOM_MESH
        assert (shape == "mesh") == is_mesh and (k >= 0) == is_mesh
        assert k < len(message["meshes"])
    # Each distinct mesh once: every entry used, fewer entries than model meshes when both
    # arms share their links' meshes.
    used = {k for k in message["mesh"] if k >= 0}
    assert used == set(range(len(message["meshes"])))
    assert len(message["meshes"]) <= len({int(model.geom_dataid[g]) for g in _mesh_geoms(model)})
    if any(model.body(i).name.startswith("left/") for i in range(model.nbody)):
        assert len(message["meshes"]) < model.nmesh


def test_mesh_entries_have_the_model_meshes_counts_and_triangles(scene):
    model, _, geometry, message = scene
    link1 = model.body("right/link1").id  # the xArm7's first link, for one
    on_link1 = 0
    for g, k in zip(geometry.geom_ids, message["mesh"], strict=True):
        if k < 0:
            continue
        entry, mesh = message["meshes"][k], int(model.geom_dataid[g])
        nv, nf = int(model.mesh_vertnum[mesh]), int(model.mesh_facenum[mesh])
        assert (entry["vertices"], entry["faces"]) == (nv, nf), model.geom(g).name
        unit, faces = decode_mesh(entry)
        f0 = model.mesh_faceadr[mesh]
        np.testing.assert_array_equal(faces, model.mesh_face[f0 : f0 + nf])
        assert unit.shape == (nv, 3) and np.abs(unit).max() <= 1.0
        # 16-bit vertices, and the faces in 16-bit indices while the mesh allows.
        assert len(base64.b64decode(entry["data"])) == 6 * nv + (-6 * nv % 4) + 6 * nf
        assert mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_MESH, entry["name"]) >= 0
        on_link1 += int(model.geom_bodyid[g] == link1)
    assert on_link1 >= 1


def test_decoded_meshes_sit_where_the_model_puts_them(scene):
    model, data, geometry, message = scene
    pose = np.array(message["pose"]).reshape(-1, 12)
    sizes = np.array(message["sizes"]).reshape(-1, 3)
    decoded = [decode_mesh(e)[0] for e in message["meshes"]]
    checked = 0
    for i, g in enumerate(geometry.geom_ids):
        k = message["mesh"][i]
        if k < 0:
            continue
        mesh = model.geom_dataid[g]
        v0, nv = model.mesh_vertadr[mesh], model.mesh_vertnum[mesh]
        expected = (
            data.geom_xpos[g] + model.mesh_vert[v0 : v0 + nv] @ data.geom_xmat[g].reshape(3, 3).T
        )
        R = pose[i, 3:].reshape(3, 3)
        drawn = pose[i, :3] + (decoded[k] * sizes[i]) @ R.T
        np.testing.assert_allclose(drawn, expected, atol=WORLD_TOLERANCE_M)
        checked += 1
    assert checked == len(_mesh_geoms(model))


def test_payload_size_is_compact(scene):
    _, _, _, message = scene
    text = json.dumps(message["meshes"])
    sent = sum(e["vertices"] * 6 + e["faces"] * 6 for e in message["meshes"])
    assert len(text) < 1.4 * sent  # base64 (4/3) and names: no per-vertex JSON numbers


def test_encode_mesh_rejects_bad_meshes_and_uses_wide_indices_when_needed():
    with pytest.raises(ValueError, match="out of range"):
        encode_mesh(np.zeros((3, 3)), [[0, 1, 3]])
    with pytest.raises(ValueError, match="vertices and faces"):
        encode_mesh(np.zeros((0, 3)), np.zeros((0, 3), dtype=int))
    rng = np.random.default_rng(0)
    v = rng.uniform(-0.1, 0.3, size=(70_000, 3))
    f = rng.integers(0, len(v), size=(10, 3))
    data, centre, half = encode_mesh(v, f)
    entry = {"name": "big", "vertices": len(v), "faces": len(f), "data": base64.b64encode(data)}
    unit, faces = decode_mesh(entry)
    np.testing.assert_array_equal(faces, f)  # uint32 indices past 65536 vertices
    np.testing.assert_allclose(centre + unit * half, v, atol=np.max(half) / QUANT)
    flat = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0]], dtype=float)  # zero thickness in z
    unit, _ = decode_mesh(
        {"vertices": 3, "faces": 1, "data": base64.b64encode(encode_mesh(flat, [[0, 1, 2]])[0])}
    )
    assert np.isfinite(unit).all()


NODE = shutil.which("node")
_NODE_SCRIPT = """
import { decodeMesh } from %(module)s;
import { readFileSync } from "node:fs";
const entries = JSON.parse(readFileSync(process.argv[2], "utf8"));
const out = entries.map((e) => {
  try {
    const m = decodeMesh(e);
    return { positions: Array.from(m.positions), indices: Array.from(m.indices),
      wide: m.indices instanceof Uint32Array, normals: m.normals };
  } catch (err) {
    return { error: String(err.message || err) };
  }
});
console.log(JSON.stringify(out));
"""


@pytest.mark.skipif(NODE is None, reason="node not installed (make sysdeps installs nodejs)")
def test_the_pages_decoder_reads_the_same_triangles_and_refuses_damaged_ones(scene, tmp_path):
    _, _, _, message = scene
    entry = min(message["meshes"], key=lambda e: e["faces"])
    raw = base64.b64decode(entry["data"])
    bad_index = bytearray(raw)
    start = 6 * entry["vertices"] + (-6 * entry["vertices"] % 4)
    bad_index[start : start + 2] = (entry["vertices"] + 5).to_bytes(2, "little")
    entries = [
        entry,
        {**entry, "data": base64.b64encode(raw[:-2]).decode()},  # truncated
        {**entry, "data": base64.b64encode(bytes(bad_index)).decode()},  # index past the end
        {**entry, "faces": "12"},  # wrong type
        {**entry, "data": "not base64!"},
    ]
    (tmp_path / "entries.json").write_text(json.dumps(entries))
    script = tmp_path / "decode.mjs"
    module = json.dumps((Path(STATIC_DIR) / "twin_gl.js").as_uri())
    script.write_text(_NODE_SCRIPT % {"module": module})
    result = subprocess.run(
        [NODE, str(script), str(tmp_path / "entries.json")],
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert result.returncode == 0, result.stderr
    good, *bad = json.loads(result.stdout)
    unit, faces = decode_mesh(entry)
    np.testing.assert_allclose(np.array(good["positions"]).reshape(-1, 3), unit, atol=1e-6)
    np.testing.assert_array_equal(np.array(good["indices"]).reshape(-1, 3), faces)
    assert not good["wide"] and good["normals"] is None  # 16-bit indices; drawn flat
    assert all("error" in r for r in bad), bad
    assert "bytes for" in bad[0]["error"] and "vertex" in bad[1]["error"]
    assert "counts" in bad[2]["error"]


class _Page:
    """A page server that keeps what it is given to publish, as the page would read it."""

    def __init__(self) -> None:
        self.published: list[tuple[str, dict]] = []

    def publish(self, kind: str, message: dict) -> None:
        self.published.append((kind, json.loads(encode_page_message(message))))


def test_the_twin_carried_between_processes_reaches_the_page_as_one_process_sends_it():
    """``--multiprocess``: the twin process's feed and the operator's relay give the page the
    same ``scene`` and ``twin`` messages as one process's ``TwinFeed`` (the status from the
    operator's pause and commands), at the same rate, never a pose before the scene; a scene
    that is no JSON is dropped and counted; the wire refuses a pose that is no whole number of
    geoms or not finite."""
    from types import SimpleNamespace

    import zmq

    from beavr_sim.headset.webxr_scene import TwinFeed
    from beavr_sim.teleop.twin_page_stream import (
        POSES_TOPIC,
        SCENE_TOPIC,
        PageTwinRelay,
        TwinPageFeed,
        TwinPageStream,
    )
    from beavr_sim.wire.messages import TwinPosesMsg, TwinSceneMsg
    from beavr_sim.wire.ports import PortConfig, TransportConfig
    from beavr_sim.wire.records import JointCommand, Tick, TwinState
    from beavr_sim.wire.transport import Publisher

    env = gym.make("beavr_sim/PickupBox-v0", embodiment="rx1").unwrapped
    env.reset(seed=0)
    home = env.agent_pos
    env.step(home + np.random.default_rng(0).normal(0, 0.1, home.shape).astype(np.float32))
    operator = SimpleNamespace(paused=True)
    names = [e.name for e in env.embodiment.effectors]
    commands = {n: JointCommand(n, np.zeros(1), 0.0, 0.0) for n in names}
    commands[names[0]] = JointCommand(names[0], np.zeros(1), 0.0, 0.0, True, "ik_infeasible")
    q = env.agent_pos
    state = TwinState(1.25, q, q, q, False, False, False, False)
    info = {"task": env.task.name, "embodiment": env.embodiment.name}
    one = _Page()
    TwinFeed(one, env.render_model, env.data, 15.0, operator, info, clock=lambda: 0.0)(
        Tick(1.25, (), commands, state)
    )
    feed = TwinPageFeed(env, TwinPageStream(15.0), clock=lambda: 0.0)
    feed(state)
    poses = feed.take()
    feed(state)  # not due again within the period: nothing new
    assert poses is not None and feed.take() is None
    context = zmq.Context()
    transport = TransportConfig(ports=PortConfig.free())
    publisher = Publisher(context, transport.endpoint("robot_state", bind=True))
    page = _Page()
    relay = PageTwinRelay(context, transport, page, operator)
    try:
        relay.note(commands)
        assert publisher.wait_for_subscribers(2, 10.0)

        def relay_when_arrived(*sockets) -> None:
            for socket in sockets:
                assert socket.poll(10_000, zmq.POLLIN), "nothing arrived"
            relay.relay()

        publisher.send(SCENE_TOPIC, TwinSceneMsg(message="{not json"))
        publisher.send(POSES_TOPIC, poses)
        relay_when_arrived(relay.scene.socket, relay.poses.socket)
        assert relay.bad_scenes == 1  # dropped, counted, never raised
        assert page.published == []  # no pose before the scene
        publisher.send(SCENE_TOPIC, feed.scene)
        publisher.send(POSES_TOPIC, poses)
        relay_when_arrived(relay.scene.socket, relay.poses.socket)
    finally:
        relay.close()
        publisher.close()
        context.term()
        env.close()
    assert [kind for kind, _ in page.published] == ["scene", "twin"]
    assert page.published == one.published
    assert one.published[1][1]["paused"] is True
    assert one.published[1][1]["holds"] == {names[0]: "ik_infeasible"}
    for bad in ([0.0] * 11, [float("nan")] * 12):
        with pytest.raises(ValueError, match="pose"):
            TwinPosesMsg(t=0.0, pose=bad)
