"""The quick start in another world model (`--checkpoint`, e.g. an MLP one): its options name that model, and its
products stay float32 where only RWM models have bf16 ones."""

from __future__ import annotations

import json
from pathlib import Path

from script_loader import EXAMPLES, load_script

from rwm_gym.resources import assets_dir


def test_the_quick_start_trains_in_the_model_it_is_given_at_the_precision_it_has():
    quickstart = load_script(EXAMPLES / "quickstart.py", "example_quickstart_engine")
    recipe = json.loads((assets_dir() / "policies" / "anymal_d_ppo_quickstart.json").read_text())
    assert quickstart.ppo_options(recipe, Path("mlp.safetensors"))[:2] == ["--checkpoint", "mlp.safetensors"]
    assert quickstart.ppo_options(recipe)[1].endswith("anymal_d_rwm_taught.safetensors")
    assert quickstart.default_precision("cuda", "mlp") == quickstart.default_precision("cpu", "mlp") == "float32"
    assert quickstart.default_precision("cuda", "rwm") == "bfloat16"
