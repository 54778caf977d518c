// Where the user moved the in-scene camera panels: one offset (world frame, metres, Z up) added
// to every panel's place as the server sends it (docs/cameras.md). Stepped by the page's
// buttons or keys, kept in the page's localStorage so the panels stay where they were put.
// A stored value that is not three finite numbers is ignored (no offset).

// The operator faces world +x: their right is world -y, up is +z, nearer is -x.
export const DIRECTIONS = {
  right: [0, -1, 0], left: [0, 1, 0], up: [0, 0, 1], down: [0, 0, -1],
  nearer: [-1, 0, 0], farther: [1, 0, 0],
};
export const STEP_M = 0.1;
// Each axis at most this far from where the server places the panels.
export const LIMIT_M = 3.0;
const KEY = "beavr_sim.cameraPanelOffset";

export class PanelOffset {
  // storage: the page's localStorage (anything with getItem / setItem), or null.
  constructor(storage) {
    this.storage = storage;
    this.key = KEY;
    this.value = [0, 0, 0];
    let stored = null;
    try {
      stored = storage ? JSON.parse(storage.getItem(KEY)) : null;
    } catch {
      stored = null;
    }
    if (Array.isArray(stored) && stored.length === 3 &&
        stored.every((v) => typeof v === "number" && Number.isFinite(v))) {
      this.value = stored.map(clamp);
    }
  }

  // One step towards `direction` (one of DIRECTIONS' names).
  step(direction, metres = STEP_M) {
    const d = DIRECTIONS[direction];
    if (!d) {
      throw new Error(`unknown panel direction ${direction}; ` +
        `choose one of ${Object.keys(DIRECTIONS).join(", ")}`);
    }
    this.set(this.value.map((v, i) => v + d[i] * metres));
  }

  reset() {
    this.set([0, 0, 0]);
  }

  set(value) {
    this.value = value.map((v) => Math.round(clamp(v) * 1e4) / 1e4);
    try {
      if (this.storage) this.storage.setItem(KEY, JSON.stringify(this.value));
    } catch {
      // storage full or refused: the offset holds for this page only
    }
  }

  // A panel's centre (world frame) moved by the offset.
  apply(center) {
    return center.map((v, i) => v + this.value[i]);
  }
}

function clamp(v) {
  return Math.max(-LIMIT_M, Math.min(LIMIT_M, v));
}
