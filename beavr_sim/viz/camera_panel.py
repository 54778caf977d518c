"""The browser view's camera panel: one image per camera (the real frame, the twin's render of
it, both side by side, or the twin blended over the real frame), its state line (live with its
age, or NO SIGNAL), the view chosen (real, twin, both, overlay) and the overlay's blend slider.

A :data:`~beavr_sim.cameras.stream.Sink` of a :class:`~beavr_sim.cameras.stream.CameraStream`:
called on the stream's worker thread, never the control thread; viser encodes the image there.
The view and blend controls set the stream's view and blend (read at its next panel).
"""

from __future__ import annotations

from collections.abc import Mapping

import numpy as np

from beavr_sim.cameras.stream import LIVE, VIEWS, CameraStream, StreamFrame, no_signal_image


class CameraPanel:
    """Adds a "Cameras" folder to ``gui`` (a viser ``GuiApi``) for ``shapes``' cameras."""

    def __init__(self, gui, shapes: Mapping[str, tuple[int, int, int]], jpeg_quality: int = 70):
        self.gui = gui
        self.images: dict[str, object] = {}
        self.labels: dict[str, object] = {}
        self.shown: dict[str, int] = {}
        self.stream: CameraStream | None = None
        with gui.add_folder("Cameras"):
            self.view = gui.add_dropdown("View", VIEWS, initial_value=VIEWS[0])
            self.blend = gui.add_slider(
                "Twin blend", min=0.0, max=1.0, step=0.05, initial_value=0.5
            )
            for name, shape in shapes.items():
                self.images[name] = gui.add_image(
                    no_signal_image(shape, name), label=name, format="jpeg",
                    jpeg_quality=jpeg_quality,
                )  # fmt: skip
                self.labels[name] = gui.add_markdown(f"**{name}**: NO SIGNAL")
                self.shown[name] = 0
        self.view.on_update(lambda _: self._set_view())
        self.blend.on_update(lambda _: self._set_blend())

    def attach(self, stream: CameraStream) -> None:
        """The stream whose view and blend the controls set."""
        self.stream = stream
        self.view.value = stream.view
        self.blend.value = stream.blend

    def _set_view(self) -> None:
        if self.stream is not None:
            self.stream.set_view(str(self.view.value))

    def _set_blend(self) -> None:
        if self.stream is not None:
            self.stream.set_blend(float(self.blend.value))

    def __call__(self, frame: StreamFrame) -> None:
        handle = self.images.get(frame.name)
        if handle is None:
            return
        handle.image = np.ascontiguousarray(frame.image)
        text = f"**{frame.label}**" if frame.state == LIVE else f"**{frame.name}: NO SIGNAL**"
        self.labels[frame.name].content = text
        self.shown[frame.name] += 1
