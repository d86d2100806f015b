"""Gate a victim's robustness in CI: its clean AP and its AP drop under an attack, on a slice of the
embedded data, as ordinary pytest assertions (runs in well under a minute on 2 CPU cores).

Requires robustbench3d installed (its pytest plugin is the ``pytest11`` entry point ``robustbench3d``;
without the entry point run ``pytest -p robustbench3d.pytest_plugin``). Replace ``fpointnet-v1-lite`` by
your registered victim (a ``robustbench3d.victims`` entry point, see examples/lidar_cluster_victim) and the
thresholds by your own measured values with some margin; the run is deterministic (seed 0), so the
numbers only move when the victim, the attack or robustbench3d changes.
"""

import pytest

# The shipped camera+LiDAR cascade with ground-truth 2D boxes (LiDAR path only), clean and under the
# shipped LiDAR-only universal object, on the first 12 frames of the embedded val split.
GATE = pytest.mark.robustbench3d(victim="fpointnet-v1-lite", attacks=["adv-shape"], proposals=["gt"], frames=12)


@GATE
def test_clean_ap_is_high_enough(robustbench3d_run):
    # Car BEV AP @ IoU 0.7, R40, moderate, in percent (measured: 93.09)
    assert robustbench3d_run.clean_ap(proposals="gt") >= 88.0


@GATE
def test_adversarial_object_costs_at_most_a_few_points(robustbench3d_run):
    # clean - attacked moderate BEV AP, percentage points (measured: 0.16)
    assert robustbench3d_run.drop("adv-shape", proposals="gt") <= 3.0
    # and in 3D (measured: 2.67)
    assert robustbench3d_run.drop("adv-shape", metric="3d", proposals="gt") <= 6.0


@GATE
def test_no_sanity_flag_but_the_slice(robustbench3d_run):
    # a 12-frame slice is flagged as such; anything else (an attack that raises AP, a victim that is not
    # deterministic, ...) fails the gate
    codes = {f["code"] for f in robustbench3d_run.flags("adv-shape", proposals="gt")}
    assert codes <= {"partial-split"}
