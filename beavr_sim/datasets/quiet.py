"""Quiet dataset writes: no encoder banners, no progress bars of the ``datasets`` library.

LeRobot encodes videos with SVT-AV1 through PyAV; the encoder writes a banner of about 20
lines (``Svt[info]: ...``) to stderr for every video file it opens, which is one per episode
and camera, and LeRobot's parquet writes run ``datasets.map`` with a ``Map`` progress bar.
:func:`quiet_dataset_writes` turns both off for this process and the processes it starts
(through the environment): SVT-AV1 then logs errors only. A variable the user set wins.
Call it before the first episode is written, and before ``datasets`` is imported: the
variable then has priority over LeRobot's ``SuppressProgressBars``, which turns the bars back
on after its own writes (the warning that it cannot is filtered out). Imported earlier, the
bars are only turned off until LeRobot turns them on.
"""

from __future__ import annotations

import os
import warnings

#: SVT-AV1's log level variable (0 fatal, 1 error, 2 warn, 3 info, 4 debug) and ours.
SVT_LOG_ENV = "SVT_LOG"
SVT_ERRORS_ONLY = "1"
#: The ``datasets`` library's switch for its progress bars, read when it is imported.
DATASETS_BARS_ENV = "HF_DATASETS_DISABLE_PROGRESS_BARS"


def quiet_dataset_writes() -> None:
    """Encoder banners and ``Map`` bars off (idempotent; see the module docstring)."""
    os.environ.setdefault(SVT_LOG_ENV, SVT_ERRORS_ONLY)
    os.environ.setdefault(DATASETS_BARS_ENV, "1")
    warnings.filterwarnings("ignore", message="Cannot enable progress bars", category=UserWarning)
    try:
        import datasets
    except ImportError:  # no LeRobot dataset extra: nothing to quiet
        return
    if os.environ[DATASETS_BARS_ENV].strip().lower() in ("1", "true", "yes", "on"):
        datasets.disable_progress_bars()
