"""The node edge's sensor-health scan (nodes._common.BlockGate) is fed a second of blocks at a time;
what is still pending when the diagnostics read it is scanned then, so a short stream's bad
channel is reported as the offline scan of the same samples reports it."""
import numpy as np

from maglev_ros.contract import TOPIC_VEHICLE_GAP
from maglev_ros.health import TopicScan
from maglev_ros.nodes._diagnostics import WARN
from maglev_ros.sensor_block import Block


class _Logger:
    def __init__(self):
        self.said = []

    def warning(self, text):
        self.said.append(text)


class _Node:
    def __init__(self):
        self.logger = _Logger()

    def get_logger(self):
        return self.logger


class _Diagnostics:
    def add_check(self, check):
        pass


def test_a_short_streams_out_of_range_gap_is_reported_as_the_offline_scan_reports_it():
    from maglev_ros.nodes._common import SCAN_BATCH_S, BlockGate
    fs = 1000.0
    rng = np.random.default_rng(0)
    gap = np.column_stack([0.010 + 1e-5 * rng.standard_normal(300),       # M1G: a levitation gap
                           0.500 + 1e-5 * rng.standard_normal(300)])      # M2G: 0.5 m, beyond 0.1 m
    assert gap.shape[0] / fs < SCAN_BATCH_S                               # shorter than one batch
    gate = BlockGate(_Node(), _Diagnostics())
    for k in range(3):
        gate._scan(TOPIC_VEHICLE_GAP, Block(k * 100_000_000, "", fs, ("M1G", "M2G"), ("m", "m"),
                                            gap[100 * k:100 * (k + 1)].astype(np.float32)))
    check = gate.health_check()
    offline = TopicScan(TOPIC_VEHICLE_GAP, ("M1G", "M2G"), fs)
    offline.add(gap.astype(np.float32))
    assert check.level == WARN and "M2G implausible" in check.message
    assert [(i.channel, i.kind) for i in offline.issues()] == [("M2G", "implausible")]
    assert "M1G" not in check.message
