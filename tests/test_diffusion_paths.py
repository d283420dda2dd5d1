"""One place for the diffusion models' default paths; an empty DIAMOND_SSS_CACHE reads as unset."""

import pytest

from diamond_sss.diffusion.common.paths import cache_root, default_cache_dir, shipped_model_dir
from diamond_sss.diffusion.nvs.pipeline import default_model_dir
from diamond_sss.diffusion.relight.inference import default_cache_root, shipped_model_path


@pytest.mark.parametrize("value", [None, ""])
def test_an_unset_or_empty_cache_variable_gives_the_home_cache(monkeypatch, tmp_path, value):
    monkeypatch.setenv("HOME", str(tmp_path))
    if value is None:
        monkeypatch.delenv("DIAMOND_SSS_CACHE", raising=False)
    else:
        monkeypatch.setenv("DIAMOND_SSS_CACHE", value)
    home_cache = tmp_path / ".cache" / "diamond_sss"
    assert cache_root() == home_cache
    assert default_cache_dir("nvs") == home_cache / "nvs"
    assert default_cache_root() == home_cache / "relight"


def test_the_cache_variable_moves_both_caches(monkeypatch, tmp_path):
    monkeypatch.setenv("DIAMOND_SSS_CACHE", str(tmp_path / "c"))
    assert default_cache_dir("nvs") == tmp_path / "c" / "nvs"
    assert default_cache_root() == tmp_path / "c" / "relight"


def test_the_shipped_models_are_found_in_the_package():
    assert default_model_dir() == shipped_model_dir("nvs")
    assert shipped_model_path() == shipped_model_dir("relight")
    for kind in ("nvs", "relight"):
        folder = shipped_model_dir(kind)
        assert folder.parts[-3:] == ("assets", "models", kind)
        assert (folder / "model.safetensors").is_file()


def test_an_unknown_model_kind_is_named():
    with pytest.raises(ValueError, match="'depth'"):
        shipped_model_dir("depth")
    with pytest.raises(ValueError, match="'depth'"):
        default_cache_dir("depth")
