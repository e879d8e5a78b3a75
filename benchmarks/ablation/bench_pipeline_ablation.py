"""Ablation of the registration pipeline's additions on datalists with ground truth (e.g. the held-out real-CT
pairs of ``bench_real_ct.py``): the default path, without the last level at native resolution (``native_level``),
with the couches kept (``keep_couch``) and bare (no global search, couch kept, no last level), on the same cases in
one run; mean TRE over the evaluation's body points. The native level is switched explicitly per variant, so the
result does not depend on the registrar's default.

Usage::

    python -m benchmarks.ablation.bench_pipeline_ablation 6 \
        bench_out/real_ct/thorax_4dct_phase00_itkelastix/dataset.json bench_out/real_ct/head_tigre_ct/dataset.json

(the first number: cases per datalist).
"""
import sys

import numpy as np
import torch

from monai_rigidreg.core.geometry import target_registration_error
from monai_rigidreg.evaluation.evaluate import iter_cases, load_datalist
from monai_rigidreg.registration.registrar import RigidRegistrar

torch.set_num_threads(2)
reg = RigidRegistrar.from_bundle(device="cpu")
variants = {"default+native": ({"native_level": True}, {}), "default": ({"native_level": False}, {}),
            "keep_couch+native": ({"native_level": True}, {"keep_couch": True}),
            "bare": ({"native_level": False}, {"keep_couch": True, "global_init": False})}
res = {k: [] for k in variants}
n = int(sys.argv[1])
for ds in sys.argv[2:]:
    items, _ = load_datalist(ds)
    for i, case in enumerate(iter_cases(items)):
        if i >= n:
            break
        row = [case.case_id]
        for k, (attrs, kw) in variants.items():
            reg.native_level = attrs.get("native_level", True)
            r = reg(case.fixed, case.moving, moving_fov=case.fov, resample_moving=False, assess=False, **kw)
            t = float(target_registration_error(r.params, case.truth, case.points, center=case.center))
            res[k].append(t)
            row.append(f"{k}={t:.2f}")
        print(" ".join(row), flush=True)
for k, v in res.items():
    print(k, f"mean {np.mean(v):.3f} median {np.median(v):.3f}")
print("machine load (1/5/15 min):", " ".join(f"{x:.2f}" for x in __import__("os").getloadavg()))
