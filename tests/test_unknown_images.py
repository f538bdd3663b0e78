"""Images whose making was not recorded (an import without a processing block) are their own kind:
not 'raw', so a fine-tune of a model of other images is refused, naming the way out."""

from __future__ import annotations

from types import SimpleNamespace

import pytest
import torch

from sonarset import SonarSetError
from sonarset.format.attrs import Processing
from sonarset.models.echopt.config import make_config
from sonarset.models.echopt.model import EchoPT
from sonarset.models.echopt.train_model import init_from

UNKNOWN = Processing(profile="unknown")


def test_unknown_images_match_only_unknown_images():
    assert not UNKNOWN.same_images(Processing.raw()) and not Processing.raw().same_images(UNKNOWN)
    assert not UNKNOWN.same_images(Processing.ertis())
    assert UNKNOWN.same_images(Processing(profile="unknown"))  # more recordings of one's own
    assert Processing(profile="custom").same_images(Processing.raw())  # recorded settings still compare by value
    assert "not recorded" in UNKNOWN.describe()


def test_fine_tuning_a_raw_model_on_unknown_images_is_refused_naming_the_way_out():
    torch.manual_seed(0)
    model = EchoPT(make_config("tiny", 50, 30))
    card = {"processing": Processing.raw().model_dump(mode="json")}
    mine = SimpleNamespace(processing=UNKNOWN, location="mine.zarr")
    with pytest.raises(SonarSetError) as refused:
        init_from(model, "pretrained", model, card, mine)
    message = str(refused.value)
    assert "\n" not in message and refused.value.parameter == "init"
    assert message.startswith("init pretrained: trained on 'raw' images") and "mine.zarr has 'unknown' images" in message
    assert "processing block of the import's metadata" in message and "train from scratch" in message
    init_from(model, "pretrained", model, card, SimpleNamespace(processing=Processing.raw(), location="sim.zarr"))
