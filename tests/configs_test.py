"""The recipes' objectives: the CPU recipe's configs add the handedness term, the release
configs keep the paper's objective, and ``:paper`` takes the additions away."""

import importlib

import pytest

RECIPES = ("synthetic", "humans", "categories", "own_json")
RELEASE = ("up3d", "h36m", "h36m_hourglass", "pascal3d", "pascal3d_hrnet", "cub_birds")


def config(name, arg=None):
    return importlib.import_module(f"configs.{name}").get_config(arg)


@pytest.mark.parametrize("name", RECIPES)
def test_cpu_recipes_train_one_handedness(name):
    c = config(name)
    assert c.loss.w_handedness > 0 and c.loss.handedness_margin > 0
    assert c.inference.handedness_reference == "auto"


@pytest.mark.parametrize("name", RELEASE)
def test_release_configs_keep_the_papers_objective(name):
    c = config(name)
    assert c.loss.w_handedness == 0 and c.loss.w_deformation == 0


@pytest.mark.parametrize("name", RECIPES)
def test_paper_variant_drops_the_added_terms(name):
    c = config(name, "paper")
    assert c.loss.w_handedness == 0 and c.loss.w_deformation == 0
    assert not c.loss.handedness_ramp and not c.loss.deformation_ramp
    assert c.loss.w_handedness_final is None and c.loss.w_deformation_final is None
    # only the added terms change: the rest of the recipe is the same
    full = config(name)
    for term in ("w_reprojection", "w_canonicalization"):
        assert c.loss[term] == full.loss[term]
    assert c.model == full.model and c.optim == full.optim


def test_paper_variant_composes_with_smoke():
    c = config("own_json", "smoke,paper")
    assert c.loss.w_handedness == 0 and c.loss.w_deformation == 0
    assert c.train.num_steps == config("own_json", "smoke").train.num_steps
