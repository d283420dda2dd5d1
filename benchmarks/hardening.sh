#!/bin/bash
# Bad inputs on every command -> what each prints: the table rows of benchmarks/results/hardening.md.
#   bash benchmarks/hardening.sh > rows.md    (PY: the project's python; VIDEO_PYTHONPATH: a path holding
#   imageio_ffmpeg for the MP4 row when the environment lacks it)
set -u
ROOT=$(cd "$(dirname "$0")/.." && pwd)
export PYTHONPATH=$ROOT/src OMP_NUM_THREADS=1 HF_HUB_OFFLINE=1
PY=${PY:-$ROOT/.venv/bin/python}
D=$(mktemp -d)
trap 'rm -rf "$D"' EXIT
CLI="$PY -m diamond_sss.cli.main"
$PY -c "
from pathlib import Path
from diamond_sss.data.analytic import make_capture
make_capture(Path('$D/data'), views=4, lights=2, size=12)
make_capture(Path('$D/data'), views=2, lights=1, size=12, split='test', camera_offset=0.4, light_offset=0.9)"
TINY="--set num_gaussians=200 --set lambda_lpips=0 --set raytrace_gaussians=32 --set mv_pixels_per_pair=16 --set batch_size=1 --set device=cpu"
$CLI train --data $D/data --out $D/run --iterations 6 --keep-schedule --quiet $TINY --set checkpoint_every=2 > /dev/null 2>&1
row() {  # row "label" command...
  local label="$1"; shift
  out=$("$@" 2>&1 | grep -v "^\s*$" | tail -n 3 | tr '\n' ' ' | sed "s|$D|D|g; s/|/\\|/g" | cut -c1-700)
  echo "| \`$label\` | $out |"
}
row_only() {  # row_only PATTERN "label" command...: only the output lines matching PATTERN
  local pattern="$1" label="$2"; shift 2
  out=$("$@" 2>&1 | grep -E "$pattern" | tr '\n' ' ' | sed "s|$D|D|g; s/|/\\|/g" | cut -c1-700)
  echo "| \`$label\` | $out |"
}
cp_run() { rm -rf $D/r2; cp -r $D/run $D/r2; NEWEST=$(ls -d $D/r2/checkpoints/step_* | sort | tail -n 1); }
row "train --set position_lr_init=inf" $CLI train --data $D/data --out $D/x --set position_lr_init=inf
row "train --set lambda_mask=nan" $CLI train --data $D/data --out $D/x --set lambda_mask=nan
row "train --set iterations=inf" $CLI train --data $D/data --out $D/x --set iterations=inf
echo '{"lambda_sil": NaN}' > $D/nan.json
row "train --config nan.json ({\"lambda_sil\": NaN})" $CLI train --data $D/data --out $D/x --config $D/nan.json
printf '{"lambda_sil": 0.1,\n' > $D/bad.json
row "train --config bad.json (truncated JSON)" $CLI train --data $D/data --out $D/x --config $D/bad.json
row "config --preset nope" $CLI config --preset nope
cp_run; $PY -c "import pathlib; p=pathlib.Path('$D/r2/model.safetensors'); b=p.read_bytes(); p.write_bytes(b[:len(b)//2])"
row "eval (model.safetensors cut to half)" $CLI eval --run $D/r2 --data $D/data
cp_run; echo '{"iterations": 6,' > $D/r2/config.json
row "export (config.json corrupt)" $CLI export --run $D/r2 --ply $D/x.ply
cp_run; echo '{"data": ' > $D/r2/data.json
row "render (data.json corrupt)" $CLI render --run $D/r2 --out $D/frames
cp_run; $PY -c "import pathlib; p=pathlib.Path('$NEWEST/scene.safetensors'); b=p.read_bytes(); p.write_bytes(b[:len(b)//2])"
row "train --resume (newest checkpoint's scene.safetensors cut to half)" $CLI train --data $D/data --out $D/r2 --iterations 8 --keep-schedule --quiet $TINY --set checkpoint_every=2 --resume
cp_run; echo '{"step": 4,' > $D/r2/checkpoints/latest.json
row "train --resume (latest.json corrupt)" $CLI train --data $D/data --out $D/r2 --iterations 8 --keep-schedule --quiet $TINY --set checkpoint_every=2 --resume
cp_run; echo '{"step": 4' > $NEWEST/state.json
row "train --resume (newest state.json corrupt)" $CLI train --data $D/data --out $D/r2 --iterations 8 --keep-schedule --quiet $TINY --set checkpoint_every=2 --resume
cp_run; for f in $D/r2/checkpoints/step_*/optim.safetensors; do : > $f; done
row "train --resume (every optim.safetensors empty)" $CLI train --data $D/data --out $D/r2 --iterations 8 --keep-schedule --quiet $TINY --set checkpoint_every=2 --resume
row "train --resume (a new folder, no checkpoint: trains from step 0)" $CLI train --data $D/data --out $D/fresh --iterations 2 --keep-schedule --quiet $TINY --resume
row_only "schedule|trained" "train --iterations 50 (sss3dgs preset)" $CLI train --data $D/data --out $D/short --preset sss3dgs --iterations 50 --quiet $TINY
row_only "WARNING|Traceback|Warning" "eval (no LPIPS weights)" $CLI eval --run $D/run --data $D/data --max-images 2
row "render --orbit 3 --video o.avi" $CLI render --run $D/run --out $D/o --orbit 3 --video o.avi
row "render --orbit 3 --video o.mp4 (imageio-ffmpeg missing)" $CLI render --run $D/run --out $D/o --orbit 3 --video o.mp4
row "render --orbit 3 --video o.mp4 --size 13 (imageio-ffmpeg present)" env PYTHONPATH=$ROOT/src:${VIDEO_PYTHONPATH:-} $CLI render --run $D/run --out $D/o --orbit 3 --video o.mp4 --size 13
row_only "WARNING|viewer of" "view --host 0.0.0.0 (stopped after 15 s)" timeout 15 $CLI view --run $D/run --host 0.0.0.0 --port 8765 --device cpu
row_only "WARNING|viewer of" "view (default host, stopped after 15 s)" timeout 15 $CLI view --run $D/run --port 8766 --device cpu
cp -r $D/data $D/ex; ls $D/ex/train | grep png | sed 's/\.png$//' > $D/ex/exclude_list.txt
row "info (exclude_list.txt names every image)" $CLI info --data $D/ex
rm $D/ex/exclude_list.txt; $PY -c "
import json; p='$D/ex/transforms_train.json'; d=json.load(open(p)); d['frames'][1]['width']='800'; json.dump(d, open(p,'w'))"
row "info (frame 1 width \"800\", a string)" $CLI info --data $D/ex
row "convert-free3d missing.ckpt out" $CLI convert-free3d $D/missing.ckpt $D/out
$PY -c "import torch; torch.save({'state_dict': {'foo.weight': torch.zeros(1)}}, '$D/foreign.ckpt')"
row "convert-free3d foreign.ckpt out" $CLI convert-free3d $D/foreign.ckpt $D/out
head -c 300 $D/foreign.ckpt > $D/cut.ckpt
row "convert-free3d cut.ckpt out (truncated)" $CLI convert-free3d $D/cut.ckpt $D/out
row "tune --set lambda_mask=inf" $CLI tune --data $D/data --out $D/t --set lambda_mask=inf
row "train --set densify.reset_every=0" $CLI train --data $D/data --out $D/x --set densify.reset_every=0
cp -r $D/data $D/pm; $PY -c "
import json; p='$D/pm/transforms_train.json'; d=json.load(open(p)); d['premultiplied_alpha']='yes'; json.dump(d, open(p,'w'))"
row "info (premultiplied_alpha \"yes\", a string)" $CLI info --data $D/pm
cp -r $D/data $D/ply; printf 'ply\nformat ascii 1.0\nelement vertex 8\nproperty float x\nproperty float y\nproperty float z\nend_header\n0 0 0\n1 0\n' > $D/ply/points3d.ply
row "train (points3d.ply truncated)" $CLI train --data $D/ply --out $D/x --iterations 2 --keep-schedule --quiet $TINY
row "tune --report-only --study diamond-ss (a study not in the storage)" $CLI tune --data $D/data --out $D/t2 --study diamond-ss --report-only
