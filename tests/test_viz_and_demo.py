"""The browser view uploads geometry once and moves body frames; the demo runs headless."""

from __future__ import annotations

import socket

import gymnasium as gym
import numpy as np
import pytest

from beavr_sim import demo

viser = pytest.importorskip("viser", reason="viser (extra 'viz') not installed")


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def test_twin_view_uploads_geoms_once_and_updates_poses():
    from beavr_sim.viz.twin_view import TwinView

    env = gym.make("beavr_sim/Playground-v0")
    env.reset(seed=0)
    u = env.unwrapped
    view = TwinView(u.render_model, port=_free_port())
    try:
        assert view.host == "127.0.0.1"
        n_handles = len(view.geom_handles)
        assert n_handles >= u.model.ngeom - 1  # every geom but the floor plane
        hand = u.model.body("right/palm").id
        before = np.array(view.body_frames[hand].position)
        for _ in range(10):
            env.step(demo.scripted_targets(env, 1.5))
        view.update(u.data)
        after = np.array(view.body_frames[hand].position)
        np.testing.assert_allclose(after, u.data.xpos[hand], atol=1e-6)
        assert np.linalg.norm(after - before) > 1e-3
        assert len(view.geom_handles) == n_handles
    finally:
        view.close()


def test_demo_runs_headless_for_a_moment():
    assert demo.main(["--no-viser", "--seconds", "0.3"]) == 0
