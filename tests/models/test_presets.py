"""The sLSBH defaults have one home (presets.SlsbhParams) that every reader takes them from."""

from __future__ import annotations

import pytest

from models import presets
from models.frontend import embedding, slsbh


def test_slsbh_params_fill_the_defaults_under_the_preset():
    assert presets.slsbh_params("cortexloc-default") == {"k": 1024, "s": 0.15, "seed": None, "adapt_tau": 0}
    assert presets.slsbh_params("cortexloc-grid") == {"k": 1024, "s": 0.25, "seed": None, "adapt_tau": 0}
    with pytest.raises(KeyError, match="unknown preset"):
        presets.slsbh_params("nope")


def test_the_embedder_takes_k_and_s_from_the_map_defaults():
    defaults = presets.SlsbhParams()
    conf = embedding.default_conf["slsbh"]
    assert (conf["k"], conf["s"]) == (defaults.k, defaults.s)


def test_slsbh_keeps_no_defaults_of_its_own():
    assert not hasattr(slsbh, "default_conf")
