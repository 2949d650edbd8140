"""Every policy file shipped in models/ loads through the flight code, says how it was trained, and is documented."""

from __future__ import annotations

from pathlib import Path

import pytest

from companion.policy import load_policy
from companion.spec import CAMERA_PRESETS

MODELS = Path(__file__).resolve().parent.parent / "models"
SHIPPED = sorted(p.name for p in MODELS.glob("*.pt"))


def test_the_bundle_and_its_distilled_sibling_are_shipped():
    assert {"policy.pt", "policy_flown_distill.pt"} <= set(SHIPPED)


@pytest.mark.parametrize("name", SHIPPED)
def test_a_shipped_policy_file_loads_and_is_documented(name):
    policy = load_policy(MODELS / name)
    provenance = policy.metadata.get("provenance", {})
    assert provenance.get("method"), f"{name}: provenance names no training method"
    assert f"`{name}`" in (MODELS / "README.md").read_text(), f"models/README.md does not describe {name}"


def test_the_flown_policies_carry_the_real_camera_and_say_which_recipe_made_them():
    for name, preset, method in (("policy.pt", "flown-fast", "sac_ae"), ("policy_flown_distill.pt", "flown-distill", "cnn")):
        policy = load_policy(MODELS / name)
        provenance = policy.metadata["provenance"]
        assert (provenance["preset"], provenance["method"]) == (preset, method), name
        assert provenance["camera"] == "realsense_d435" and provenance["camera_noise"], name
        assert policy.camera.hfov_deg == CAMERA_PRESETS["realsense_d435"].hfov_deg, name
        assert policy.camera.vfov_deg == CAMERA_PRESETS["realsense_d435"].vfov_deg, name
        assert provenance["recipe"]["wall_time_s"] <= 45 * 60, f"{name}: trained in more than 45 min"
