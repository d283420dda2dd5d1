"""Step checkpoint folders (trainer, fine-tunes): 8 digits; older 7-digit folders still found, ordered by step."""

import json
import shutil

import torch
from accelerate import Accelerator, debug_launcher
from accelerate.state import AcceleratorState

from diamond_sss.diffusion.common.checkpoints import (
    latest_accelerate_checkpoint,
    load_accelerate_checkpoint,
    save_accelerate_checkpoint,
)
from diamond_sss.diffusion.common.runtime import make_accelerator
from diamond_sss.training.checkpoint import checkpoint_folders, resume_checkpoint, save_checkpoint
from diamond_sss.utils.step_folders import step_folder_name


def _save(run_dir, step, **kwargs):
    weight = torch.nn.Parameter(torch.full((2,), float(step)))
    optimizer = torch.optim.Adam([weight], lr=0.1)
    weight.sum().backward()
    optimizer.step()
    return save_checkpoint(run_dir, step, {"w": weight.detach()}, {"w": optimizer}, {}, {"note": step}, **kwargs)


def _step_folders(run_dir):
    return sorted(p.name for p in (run_dir / "checkpoints").iterdir() if p.is_dir())


def test_trainer_checkpoints_keep_the_newest_two_by_default_any_number_or_every_one(tmp_path):
    for step in (1, 2, 3):
        _save(tmp_path / "default", step)
    assert _step_folders(tmp_path / "default") == ["step_00000002", "step_00000003"]
    for step in (1, 2, 3, 4):
        _save(tmp_path / "three", step, keep=3)
    assert _step_folders(tmp_path / "three") == ["step_00000002", "step_00000003", "step_00000004"]
    for step in (1, 2, 3, 4):
        _save(tmp_path / "every", step, keep=0)
    assert _step_folders(tmp_path / "every") == [f"step_0000000{step}" for step in (1, 2, 3, 4)]
    loaded = resume_checkpoint(tmp_path / "every")[1]
    assert loaded.step == 4 and torch.equal(loaded.scene["w"], torch.full((2,), 4.0) - 0.1)


def _rename_to_seven_digits(folder):
    old = folder.with_name(f"step_{int(folder.name[5:]):07d}")
    shutil.move(folder, old)
    return old


def test_step_folders_have_eight_digits():
    assert step_folder_name(500) == "step_00000500"


def test_an_old_seven_digit_trainer_checkpoint_resumes_and_is_pruned_by_step(tmp_path):
    for step in (4, 5):
        old = _rename_to_seven_digits(_save(tmp_path, step))
    (tmp_path / "checkpoints" / "latest.json").write_text(json.dumps({"step": 5, "dir": old.name}))
    found, loaded = resume_checkpoint(tmp_path)
    assert found.name == "step_0000005"
    assert loaded.step == 5 and loaded.extra == {"note": 5}
    assert torch.equal(loaded.scene["w"], torch.full((2,), 5.0) - 0.1)
    _save(tmp_path, 6)
    names = sorted(p.name for p in (tmp_path / "checkpoints").iterdir() if p.is_dir())
    assert names == ["step_00000006", "step_0000005"]
    (tmp_path / "checkpoints" / "latest.json").unlink()  # without the pointer: newest step first
    assert [p.name for p in checkpoint_folders(tmp_path)] == ["step_00000006", "step_0000005"]
    assert resume_checkpoint(tmp_path)[0].name == "step_00000006"


def test_accelerate_checkpoints_of_both_paddings_are_ordered_by_step(tmp_path):
    accelerator = make_accelerator()
    accelerator.prepare(torch.nn.Linear(2, 2))
    _rename_to_seven_digits(save_accelerate_checkpoint(accelerator, tmp_path, 12, keep=0))
    save_accelerate_checkpoint(accelerator, tmp_path, 3, keep=0)
    assert latest_accelerate_checkpoint(tmp_path).name == "step_0000012"
    save_accelerate_checkpoint(accelerator, tmp_path, 13, keep=2)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["step_00000013", "step_0000012"]


def _save_and_resume_each_process(root):
    """In each of two processes: seed its own RNG, checkpoint, draw; scramble the RNG, resume, draw again."""
    AcceleratorState._reset_state(True)  # forked from the test process: drop its single-process state
    accelerator = Accelerator(cpu=True)
    accelerator.prepare(torch.nn.Linear(2, 2))
    torch.manual_seed(100 + accelerator.process_index)
    folder = save_accelerate_checkpoint(accelerator, root, 1)
    accelerator.wait_for_everyone()
    drawn = torch.rand(3).tolist()
    torch.manual_seed(0)
    load_accelerate_checkpoint(accelerator, root / step_folder_name(1))
    again = torch.rand(3).tolist()
    (root / f"process_{accelerator.process_index}.json").write_text(
        json.dumps({"drawn": drawn, "again": again, "folder": None if folder is None else folder.name}))


def test_an_accelerate_checkpoint_resumes_the_random_state_of_every_process(tmp_path):
    debug_launcher(_save_and_resume_each_process, args=(tmp_path,), num_processes=2)
    results = [json.loads((tmp_path / f"process_{index}.json").read_text()) for index in (0, 1)]
    assert [r["folder"] for r in results] == [step_folder_name(1), None]  # the main process publishes it
    assert all(r["again"] == r["drawn"] for r in results)
    assert results[0]["drawn"] != results[1]["drawn"]
    assert sorted(p.name for p in (tmp_path / step_folder_name(1)).glob("random_states_*")) == [
        "random_states_0.pkl", "random_states_1.pkl"]
    assert not list(tmp_path.glob(".*.tmp"))
