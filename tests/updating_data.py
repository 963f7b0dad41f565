"""Simulated recordings with KNOWN (hidden) true parameters for the updating tests.

The truth differs from the nominal design (what the metadata's design block / defaults say) in the
guideway E, rho, kb (within +-15 %) and the controller gains (within +-30 %); the updater sees only the
nominal design and the measurements (with sensor noise), never the truth.
"""
from __future__ import annotations

import json
from dataclasses import dataclass, replace

import numpy as np

from maglev_ros.twin.coupling import simulate_pass
from maglev_ros.twin.design import line_spans, twin_config, with_guideway, with_levitation
from maglev_ros.twin.irregularity_psd import german_high_speed, random_profile

SPAN_M = 12.384
LINE = {"spans": [{"id": "S1", "start_m": 0.0, "length_m": SPAN_M},
                  {"id": "S2", "start_m": SPAN_M, "length_m": SPAN_M}]}
MID_S1 = 0.5 * SPAN_M


@dataclass(frozen=True)
class Truth:
    factors: dict            # parameter name -> true / nominal

    def config(self, nominal):
        g = {k: getattr(nominal.guideway, k) * v for k, v in self.factors.items() if hasattr(nominal.guideway, k)}
        l = {k: getattr(nominal.levitation, k) * v for k, v in self.factors.items() if hasattr(nominal.levitation, k)}
        return with_levitation(with_guideway(nominal, **g), **l)


def random_truth(seed: int) -> Truth:
    rng = np.random.default_rng(1000 + seed)
    f = {}
    for k in ("youngs_modulus_pa", "density_kg_m3", "bearing_stiffness_n_per_m"):
        f[k] = float(1 + rng.choice([-1, 1]) * rng.uniform(0.05, 0.15))
    for k in ("kp_a_per_m", "kv_a_s_per_m", "ka_a_s2_per_m"):
        f[k] = float(1 + rng.choice([-1, 1]) * rng.uniform(0.10, 0.30))
    return Truth(f)


def irregularity(seed: int, start_m: float = -30.0, length_m: float = 90.0):
    return random_profile(german_high_speed("low"), length_m, 0.01, (0.3, 20.0), rng=seed, start_m=start_m)


def simulate_measurement(cfg, speed_mps: float, irr_seed: int, duration_s: float, fs_hz: float = 500.0,
                         noise_seed: int = 0, accel_noise: float = 0.01, gap_noise_m: float = 5e-6,
                         disp_noise_m: float = 2e-6, start_position_m: float | None = None):
    """Dict of measured arrays (noise added) of one pass of the TRUE twin ``cfg``."""
    x, r = irregularity(irr_seed)
    res = simulate_pass(cfg, LINE, speed_mps, (x, r), sensors={"MID": MID_S1}, duration_s=duration_s,
                        fs_out_hz=fs_hz, start_position_m=start_position_m)
    rng = np.random.default_rng(noise_seed)
    n, m = res.magnet_accel_mps2.shape
    g0 = cfg.levitation.nominal_gap_m
    return {
        "time_s": res.time_s, "position_m": res.position_m, "speed_mps": res.speed_mps,
        "accel": res.magnet_accel_mps2 + accel_noise * rng.standard_normal((n, m)),
        "gap": res.magnet_gap_m + gap_noise_m * rng.standard_normal((n, m)),
        "disp_mid": res.guideway_disp_m[:, 0] + disp_noise_m * rng.standard_normal(n),
        "accel_mid": res.guideway_accel_mps2[:, 0],
        "offsets": np.asarray(cfg.vehicle.magnet_offsets_m), "g0": g0,
        "true_irregularity": (x, r), "magnet_force_static_n": None,
    }


# ------------------------------------------------------------------ online updater test data
def ambient_metadata(design: dict | None = None, n_sections: int = 5) -> dict:
    """Contract metadata of a one-span ambient record with vertical sensors at (k+1)/(n+1) of S1."""
    sensors = {}
    for k in range(n_sections):
        sensors[f"G{k + 1}LV"] = {"topic": "/testline/guideway/accel", "quantity": "acceleration",
                                  "direction": "vertical", "span": "S1",
                                  "position_m": round((k + 1) / (n_sections + 1) * SPAN_M, 6), "side": "left"}
    md = {"schema": "maglev-testline/1", "line": {"spans": [{"id": "S1", "start_m": 0.0, "length_m": SPAN_M}]},
          "sensors": sensors, "run": {"kind": "ambient"}}
    if design is not None:
        md["design"] = design
    return md


def true_modes(md: dict, factors: dict, n_modes: int = 3, f_noise: float = 2e-4, seed: int = 0) -> list[dict]:
    """Modes of the TRUE span (twin's Guideway class, independent of the updater's SpanModel) at the
    metadata's sensors, as the modal stage reports them (dicts like ModalMode)."""
    from maglev_ros.twin.design import twin_config_from_metadata
    from maglev_ros.twin.guideway import Guideway
    cfg = twin_config_from_metadata(md)
    cfg = with_guideway(cfg, **{k: getattr(cfg.guideway, k) * v for k, v in factors.items()})
    modal = Guideway(line_spans(md["line"], cfg)).modes(cutoff_hz=1e4, min_modes_per_span=n_modes,
                                                        max_modes_per_span=n_modes)
    chans = list(md["sensors"])
    xs = np.array([md["sensors"][c]["position_m"] for c in chans])
    S = modal.shapes_at(xs).T
    rng = np.random.default_rng(seed)
    out = []
    for i in range(n_modes):
        s = S[i] / np.max(np.abs(S[i]))
        out.append({"id": f"M{i + 1}", "status": "tracked",
                    "frequency_hz": float(modal.freq_hz[i] * (1 + f_noise * rng.standard_normal())),
                    "std_frequency_hz": float(f_noise * modal.freq_hz[i]), "damping_ratio": 0.02,
                    "std_damping_ratio": float("nan"), "mpc": 1.0, "channels": chans,
                    "mode_shape": (s + 0.003 * rng.standard_normal(s.size)).tolist()})
    return out


def publish_for_node(metadata_json: str, modes_json: str, hold_s: float) -> None:
    """Helper process for the node test: latched metadata + one ModalEstimate, then idle."""
    import time as _t
    import rclpy
    from rclpy.node import Node
    from std_msgs.msg import String
    from maglev_msgs.msg import ModalEstimate, ModalMode
    from maglev_ros.nodes._common import QOS_LATCHED, QOS_STREAM
    rclpy.init()
    node = Node("updater_test_pub")
    pm = node.create_publisher(String, "/testline/metadata", QOS_LATCHED)
    pe = node.create_publisher(ModalEstimate, "/maglev/modes", QOS_STREAM)
    pm.publish(String(data=metadata_json))
    end = _t.monotonic() + 20
    while pe.get_subscription_count() == 0 and _t.monotonic() < end:
        rclpy.spin_once(node, timeout_sec=0.1)
    _t.sleep(1.0)
    msg = ModalEstimate()
    msg.method = "ssi-cov"
    msg.window_s = 60.0
    for m in json.loads(modes_json):
        mm = ModalMode()
        mm.id, mm.status = m["id"], m["status"]
        mm.frequency_hz, mm.damping_ratio = m["frequency_hz"], m["damping_ratio"]
        mm.std_frequency_hz, mm.std_damping_ratio, mm.mpc = m["std_frequency_hz"], float("nan"), m["mpc"]
        mm.channels, mm.mode_shape = m["channels"], m["mode_shape"]
        msg.modes.append(mm)
    pe.publish(msg)
    end = _t.monotonic() + hold_s
    while _t.monotonic() < end:
        rclpy.spin_once(node, timeout_sec=0.1)
    node.destroy_node()
    rclpy.try_shutdown()


if __name__ == "__main__":
    import json
    import sys
    publish_for_node(open(sys.argv[1]).read(), open(sys.argv[2]).read(), float(sys.argv[3]))
