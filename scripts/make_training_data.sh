#!/usr/bin/env bash
# Simulate the data the shipped bundle weights were trained and validated on (exact commands; see
# bundles/cbct_ct_rigid/docs/README.md). Base pairs carry a small motion (<= 5 mm, 5 deg); training adds random
# motion on the fly (RandRigid6DoFd). Training CBCTs cover the whole object: a truncated field of view would move
# with the on-the-fly motion and give the motion away, so truncation is added after the motion, in the scanner
# frame, by RandCBCTDegradationd. The *_interior sets (128 mm FOV, as in the paper) are simulated for evaluation
# and excluded from train.json. Held out from training: the stock Shepp-Logan phantom, the thorax CT, the head CT
# and the random-phantom seeds of benchmarks/accuracy/bench_registration.py.
#   usage: scripts/make_training_data.sh [DATA_DIR] [SHARED_DATA_DIR]
set -euo pipefail
DATA=${1:-data}
SHARED=${2:-../shared/data}
export OMP_NUM_THREADS=1 OMP_WAIT_POLICY=PASSIVE
SIM="monai-rigidreg simulate --no-progress --protocol random --set max_translation=5 --set max_rotation=5"
GRID="--set simct_size=128 --set simct_spacing=2.0 --set simct_views=360 --set cbct_views=180"
FULL="--set cbct_size=80 --set cbct_spacing=3.0 --set projection_spacing=2.0"      # 240 mm: whole object
INTERIOR="--set cbct_size=64 --set cbct_spacing=2.0 --set projection_spacing=2.0"  # 128 mm interior FOV (paper)
NOISY="--set photons=3e4 --set scatter_to_primary=0.5 --set beam_hardening=0.02"

$SIM --output-dir "$DATA/rand_full" --phantom random --num-cases 24 --set num_objects=12 --seed 100 $GRID $FULL &
$SIM --output-dir "$DATA/rand_interior" --phantom random --num-cases 24 --set num_objects=12 --seed 200 \
    $GRID $INTERIOR $NOISY &
wait
$SIM --output-dir "$DATA/asym_full" --phantom shepp-logan-asym --num-cases 6 --seed 300 $GRID $FULL &
$SIM --output-dir "$DATA/asym_interior" --phantom shepp-logan-asym --num-cases 6 --seed 301 $GRID $INTERIOR $NOISY &
wait
# synthetic anatomy (random label maps, random tissue contrasts, texture, bias fields; simulation/synth.py), with
# the clinical-dose CBCT physics on half of them
$SIM --output-dir "$DATA/synth_full" --phantom synth --num-cases 16 --seed 500 $GRID $FULL &
$SIM --output-dir "$DATA/synth_noisy_full" --phantom synth --num-cases 16 --seed 600 $GRID $FULL $NOISY &
wait
if [ -f "$SHARED/abdomen_pelvis_totalsegmentator_example_ct.nii.gz" ]; then
    $SIM --output-dir "$DATA/abdomen" --phantom "$SHARED/abdomen_pelvis_totalsegmentator_example_ct.nii.gz" \
        --num-cases 12 --seed 400 --set simct_size=128 --set simct_spacing=3.0 --set simct_views=360 \
        --set cbct_views=180 --set cbct_size=80 --set cbct_spacing=3.0 --set projection_spacing=3.0 \
        --set photons=1e6 --set electronic_noise=2.0 --set scatter_to_primary=0.2 \
        --set ct_frame=False  # pelvis: clinical-like dose; centred on the origin, as the shipped weights saw it
fi
# validation: the paper protocol on the stock phantom (held out), interior 128 mm FOV as in the paper
monai-rigidreg simulate --no-progress --output-dir "$DATA/val_paper" --phantom shepp-logan --protocol paper \
    --num-cases 21 --seed 900 $GRID $INTERIOR
python - "$DATA" <<'PY'
import json, sys
from pathlib import Path
root = Path(sys.argv[1])
items = []
# the simulate datasets only (scripts/make_clinical_training_data.py writes its own datalist under clinical/)
for sub in sorted(p for p in root.iterdir() if p.is_dir() and p.name not in ("val_paper", "clinical")
                  and "interior" not in p.name and (p / "dataset.json").is_file()):
    for it in json.loads((sub / "dataset.json").read_text())["training"]:
        for k in ("fixed", "moving", "moving_fov"):
            it[k] = f"{sub.name}/{it[k]}"
        items.append(it)
(root / "train.json").write_text(json.dumps({"training": items}, indent=1))
print(f"{len(items)} training base pairs -> {root / 'train.json'}")
PY
