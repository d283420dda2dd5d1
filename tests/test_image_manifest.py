"""One manifest of generated images for both diffusion models: round trip, the older novel-view layout, errors."""

import json

import pytest

from diamond_sss.diffusion.common.manifest import (
    GeneratedImage,
    image_paths,
    read_image_manifest,
    write_image_manifest,
)


def test_write_then_read_gives_the_same_images(tmp_path):
    items = [GeneratedImage(3, 1, *image_paths(tmp_path, "view_003")),
             GeneratedImage(2, 5, *image_paths(tmp_path, "v002_l005"))]
    path = write_image_manifest(tmp_path, items)
    assert json.loads(path.read_text()) == [
        {"view": 3, "light": 1, "image": "images/view_003.png", "mask": "masks/view_003.png"},
        {"view": 2, "light": 5, "image": "images/v002_l005.png", "mask": "masks/v002_l005.png"},
    ]
    assert read_image_manifest(path) == items


def test_a_view_off_the_lattice_is_written_and_read_as_null(tmp_path):
    items = [GeneratedImage(None, 2, *image_paths(tmp_path, "pose_000"))]
    path = write_image_manifest(tmp_path, items)
    assert json.loads(path.read_text())[0]["view"] is None
    assert read_image_manifest(path) == items


def test_an_older_novel_view_folder_reads_with_its_own_paths(tmp_path):
    (tmp_path / "manifest.json").write_text(json.dumps(
        [{"view": 1, "light": 0, "image": "view_001.png", "mask": "view_001_mask.png"}]))
    assert read_image_manifest(tmp_path / "manifest.json") == [
        GeneratedImage(1, 0, tmp_path / "view_001.png", tmp_path / "view_001_mask.png")]


@pytest.mark.parametrize(("content", "message"), [
    ("{", "not valid JSON"),
    ('{"view": 1}', "must hold a list"),
    ('[{"view": 1, "light": 0, "image": "a.png"}]', r"entry 0: .*\['mask'\]"),
    ('[{"light": 0, "image": "a.png", "mask": "m.png"}]', r"entry 0: .*\['view'\]"),
    ('[{"view": 1, "light": null, "image": "a.png", "mask": "m.png"}]', r"entry 0: .*\['light'\]"),
    ('[{"view": "1", "light": 0, "image": "a.png", "mask": "m.png"}]', r"entry 0: .*\['view'\]"),
    ('[3]', r"entry 0: .*\['view', 'light', 'image', 'mask'\]"),
])
def test_a_bad_manifest_names_the_file_entry_and_key(tmp_path, content, message):
    (tmp_path / "manifest.json").write_text(content)
    with pytest.raises(ValueError, match=message) as error:
        read_image_manifest(tmp_path / "manifest.json")
    assert str(tmp_path / "manifest.json") in str(error.value)


def test_an_image_without_a_mask_is_refused(tmp_path):
    with pytest.raises(ValueError, match="needs a mask"):
        write_image_manifest(tmp_path, [GeneratedImage(0, 0, tmp_path / "images" / "a.png")])
