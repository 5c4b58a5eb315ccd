"""benchmarks/critical_path.py's sleeping probe: MuJoCo Warp's sleeping reaches the device
model and data of the batch inside the probe, and nothing of it outlives the probe (the other
variants of the same run, and the caller's MuJoCo model, stay as they were)."""

from __future__ import annotations

import sys
from pathlib import Path

import mujoco
import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))

mjw = pytest.importorskip("mujoco_warp")
import critical_path  # noqa: E402

SLEEP = int(mujoco.mjtEnableBit.mjENBL_SLEEP)
SCENE = """<mujoco><worldbody><geom type="plane" size="1 1 .1"/>
<body pos="0 0 .1"><freejoint/><geom type="box" size=".05 .05 .05"/></body>
</worldbody></mujoco>"""


def test_the_probe_enables_sleeping_on_the_device_and_restores_everything():
    mjm = mujoco.MjModel.from_xml_string(SCENE)
    before = int(mjm.opt.enableflags)
    put_model, put_data = mjw.put_model, mjw.put_data
    with critical_path.sleeping(True):
        m = mjw.put_model(mjm)
        d = mjw.put_data(mjm, mujoco.MjData(mjm), nworld=2)
        assert int(m.opt.enableflags) & SLEEP
        assert int(mjm.opt.enableflags) == before  # the caller's model is left alone
    assert (mjw.put_model, mjw.put_data) == (put_model, put_data)
    assert tuple(d.tree_awake.shape) == (2, mjm.ntree)
    assert not int(mjw.put_model(mjm).opt.enableflags) & SLEEP


def test_the_variants_that_are_not_probes_leave_sleeping_off():
    mjm = mujoco.MjModel.from_xml_string(SCENE)
    put_model = mjw.put_model
    with critical_path.sleeping(False):
        assert mjw.put_model is put_model
        assert not int(mjw.put_model(mjm).opt.enableflags) & SLEEP
    assert {v for v, kw in critical_path.VARIANTS.items() if kw.get("sleep")} == {
        "fixed_sleep",
        "paced_sleep",
    }
