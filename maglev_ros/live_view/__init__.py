"""The live view: what the Foxglove bridge node shows, as pure functions of the suite's results.

No rclpy and no foxglove import here: the node (``maglev_ros.nodes.foxglove_bridge``) turns ROS
messages into core Blocks / dicts, feeds them to this package and logs what comes out.

- :mod:`.decimate`: per display bin, min / max / mean of each channel (time series for plots);
- :mod:`.residual_map`: residual RMS per (position bin, band) over the line;
- :mod:`.messages`: modes (and their history), mismatch events, diagnosis, parameters, profile;
- :mod:`.scene`: the 3D scene (guideway spans, sensors, vehicle, mismatch zones).

The display channels' names are fixed (``/maglev/view/...``): a graph in a namespace serves the
same channel names on its own port, so one layout fits every line.
"""
from __future__ import annotations

from maglev_ros.contract import (TOPIC_BODY_ACCEL, TOPIC_GUIDEWAY_ACCEL,
                                 TOPIC_GUIDEWAY_DISP, TOPIC_VEHICLE_ACCEL, TOPIC_VEHICLE_GAP,
                                 TOPIC_VEHICLE_POSITION)

# the twin's output groups and topics (maglev_ros.twin.online's; not imported from there, since it
# loads numba, seconds of start-up for a viewer; a test keeps the two equal)
GROUP_TOPICS = {"guideway_accel": TOPIC_GUIDEWAY_ACCEL, "guideway_displacement": TOPIC_GUIDEWAY_DISP,
                "vehicle_accel": TOPIC_VEHICLE_ACCEL, "vehicle_gap": TOPIC_VEHICLE_GAP,
                "body_accel": TOPIC_BODY_ACCEL}
PREDICTED_PREFIX = "/maglev/twin/predicted/"
RESIDUAL_PREFIX = "/maglev/twin/residual/"

VIEW_PREFIX = "/maglev/view/"
KINDS = ("measured", "predicted", "residual")
POSITION_GROUP = "vehicle_position"
# display group of each measured contract topic (the twin's group names; position has no twin group)
MEASURED_GROUPS = {**{t: g for g, t in GROUP_TOPICS.items()}, TOPIC_VEHICLE_POSITION: POSITION_GROUP}
TWIN_GROUPS = tuple(GROUP_TOPICS)

VIEW_MODES = VIEW_PREFIX + "modes"
VIEW_MODE_HISTORY = VIEW_PREFIX + "modes/history"
VIEW_MISMATCH = VIEW_PREFIX + "mismatch"
VIEW_MISMATCH_LOG = VIEW_PREFIX + "mismatch/log"
VIEW_DIAGNOSIS = VIEW_PREFIX + "diagnosis"
VIEW_PARAMETERS = VIEW_PREFIX + "parameters"
VIEW_IRREGULARITY = VIEW_PREFIX + "irregularity"
VIEW_METADATA = VIEW_PREFIX + "metadata"
VIEW_SCENE = VIEW_PREFIX + "scene"                  # foxglove.SceneUpdate
VIEW_TF = VIEW_PREFIX + "tf"                        # foxglove.FrameTransform line -> vehicle
# the results the bridge sends again, as they are now, to a client that subscribes late
LATCHED_VIEWS = (VIEW_MODES, VIEW_MODE_HISTORY, VIEW_MISMATCH, VIEW_MISMATCH_LOG, VIEW_DIAGNOSIS,
                 VIEW_PARAMETERS, VIEW_IRREGULARITY, VIEW_METADATA)


def series_topic(group: str, kind: str) -> str:
    """``/maglev/view/<group>/<measured|predicted|residual>``: decimated time series."""
    return f"{VIEW_PREFIX}{group}/{kind}"


def map_topic(group: str) -> str:
    """``/maglev/view/<group>/residual_map``: residual RMS per (band, position bin), JSON."""
    return f"{VIEW_PREFIX}{group}/residual_map"


def map_grid_topic(group: str) -> str:
    """``/maglev/view/<group>/residual_map/grid``: the same map as a foxglove.Grid beside the line."""
    return f"{VIEW_PREFIX}{group}/residual_map/grid"


def source_topics() -> dict[str, tuple[str, str]]:
    """Every suite topic a stream series comes from: topic -> (group, kind)."""
    out = {t: (g, "measured") for t, g in MEASURED_GROUPS.items()}
    for g in TWIN_GROUPS:
        out[PREDICTED_PREFIX + g] = (g, "predicted")
        out[RESIDUAL_PREFIX + g] = (g, "residual")
    return out


def view_topics() -> set[str]:
    """Every channel the bridge can advertise (a stream's channels appear with its first block)."""
    out = {series_topic(g, k) for g, k in source_topics().values()}
    out |= {map_topic(g) for g in TWIN_GROUPS} | {map_grid_topic(g) for g in TWIN_GROUPS}
    out |= {VIEW_SCENE, VIEW_TF, *LATCHED_VIEWS}
    return out

