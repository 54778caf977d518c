"""Is a recorded mirrored episode true? Its measured ``observation.state`` read back from disk
against its ``action``, by the rig's own rule (imported as ``from recorded_state import ...``:
``tests/`` is on the path)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

#: How far the measured joints may be from the commands in a true episode (rad), and for how
#: many frames in a row: the rig's own limits (``MirrorConfig``: arm 0.3, hand 0.8 rad, for at
#: most its 0.5 s divergence window, 15 frames at 30 fps). A device may trail further for less
#: than the window (a busy machine delays a writer; the arm then catches up at its speed cap);
#: a frozen or stale state stays away (and fails the "moving with them" check).
ARM_GAP_RAD = 0.3
HAND_GAP_RAD = 0.8
WINDOW_FRAMES = 15
#: ... from the commands of the last quarter second (MirrorConfig.device_lag_s) at 30 fps.
LAG_FRAMES = 8


def _longest_run(over: np.ndarray) -> tuple[int, int]:
    """The longest stretch of consecutive True frames: (its length, its first frame)."""
    best, start, run = 0, 0, 0
    for k, flag in enumerate(over):
        run = run + 1 if flag else 0
        if run > best:
            best, start = run, k - run + 1
    return best, start


def check_follows(state: np.ndarray, action: np.ndarray, names: list[str], episode: int) -> None:
    """The measured state follows the command: within the rig's rule
    (:func:`check_within_rule`) and moving with them."""
    check_within_rule(state, action, names, episode)
    # Not frozen: the joint the command moves most moves about as much measured.
    j = int(np.argmax(np.ptp(action, axis=0)))
    assert np.ptp(action[:, j]) > 0.3, "the episode should move the robot"
    assert np.ptp(state[:, j]) >= 0.7 * np.ptp(action[:, j]), (episode, names[j] if names else j)


def check_within_rule(
    state: np.ndarray, action: np.ndarray, names: list[str], episode: int
) -> None:
    """Never further than the rig's limit from the commands of the last ``LAG_FRAMES`` (a
    device trails its commands by a few periods) for longer than its window."""
    hand = np.array(["leap" in n for n in names]) if names else np.zeros(action.shape[1], bool)
    gap = np.zeros_like(state)
    for k in range(len(state)):
        recent = action[max(0, k - LAG_FRAMES) : k + 1]
        gap[k] = np.maximum(np.maximum(recent.min(0) - state[k], state[k] - recent.max(0)), 0)
    for part, limit in ((~hand, ARM_GAP_RAD), (hand, HAND_GAP_RAD)):
        if not part.any():
            continue
        frames, first = _longest_run(gap[:, part].max(axis=1) > limit)
        assert frames <= WINDOW_FRAMES, (
            f"episode {episode}: measured joints over {limit} rad from the commands for "
            f"{frames} frames from frame {first} (largest gap {gap[:, part].max():.3f} rad)"
        )


def read_episodes(root: Path, repo_id: str) -> dict[int, tuple[np.ndarray, np.ndarray, list[str]]]:
    """Per saved episode: (observation.state, action, joint names), read back from disk."""
    from lerobot.datasets.lerobot_dataset import LeRobotDataset

    ds = LeRobotDataset(repo_id, root=root, video_backend="pyav")
    names = list(ds.features["action"]["names"] or [])
    state = np.array(ds.hf_dataset["observation.state"])
    action = np.array(ds.hf_dataset["action"])
    index = np.array(ds.hf_dataset["episode_index"])
    return {int(e): (state[index == e], action[index == e], names) for e in np.unique(index)}
