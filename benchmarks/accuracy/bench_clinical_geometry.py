"""Registration in clinical geometry on real CTs (issue 15): the network's default path, elastix and SimpleITK.

The paper protocol moves the patient about the CT centre. A physicist's pairs do not: the CBCT is centred on the
treatment isocentre somewhere inside a larger planning CT, couch and setup offsets reach several centimetres, the
anatomy changes between the scans, and the match is judged on the target region. This benchmark builds such pairs
from the real CTs of ``../shared/data`` with :mod:`monai_rigidreg.simulation.clinical` (frames, conventions and
the simulation are described there). The CTs (see their ``.txt`` sidecars):

* ``thorax_4dct_phase00_itkelastix``: a radiotherapy planning CT of the thorax with the couch (held out of
  training);
* ``head_tigre_ct``: a CT-derived head with real skull geometry but a flat soft-tissue plateau (held out; a
  deformation there shows only at bone, sinus and skin edges);
* ``abdomen_pelvis_totalsegmentator_example_ct``: used in training of the shipped network, reported separately.

The pairs:

* the planning CT (fixed) is the real CT itself, on its own grid;
* the isocentre lies inside the body (>= 10 mm deep) at a distance from the CT centre drawn uniformly in 0-100 mm,
  with the CBCT's axial extent inside the CT's slices;
* the setup error (fixed -> moving) is a rotation about the isocentre plus a translation (table shift);
* the CBCT (moving; 128 x 128 x 80 voxels at 2 mm: a 256 mm diameter, 160 mm long cylindrical field of view,
  centred on the isocentre) is simulated in the projection domain from the moved patient (cone beam, 180 views,
  noise, scatter, beam hardening, FDK);
* groups: ``small`` (|t| 0-40 mm, every angle within +-30 degrees), ``large`` (the band beyond: |t| 40-60 mm, every
  angle within +-45 degrees and the largest 30-45), ``deformed`` (as ``small``, and the anatomy near the isocentre
  deformed smoothly before the setup error, peak 5-15 mm, zero elsewhere).

Each pair is registered by every method in the same run, with the volumes in memory:

* ``network``: the product's default path, ``monai_rigidreg.register(ct, cbct, model=registrar,
  moving_fov=fov, resample_moving=False)`` with ``registrar = RigidRegistrar.from_bundle(device=...)``; on deformed
  pairs also ``roi=`` (the target box, CT LPS mm) when ``register`` accepts it;
* ``network-thorough`` (optional): the same with ``thorough=True`` (the global search, further starts and the
  swapped-input estimate on every pair, the default path before 0.5.0.dev); for both network methods the report lists
  the path taken, how often the network-led path's fallback ran and why, every pair's check and the stage medians;
* ``elastix``: ``monai_rigidreg.registration.classical.register_elastix`` (elastix's default rigid map; the CT sampled
  where the CBCT's field of view lies at the identity, ``moving_mask=fov``);
* ``sitk``: ``monai_rigidreg.registration.classical.register_sitk`` (Mattes MI, masked to the field of view);
* ``elastix-roi`` (optional): ``register_elastix`` with the CT samples restricted to the target box (deformed pairs
  only; elastix as a physicist would use it for a target-region match);
* ``ants``, ``greedy`` (optional, the ``bench`` extra): the peer tools, ``monai_rigidreg.registration.peers``
  (``moving_mask=fov``, or none with ``--peer-mask none``), each counted only after its convention check passes.

Errors:

* TRE: mean ``|T_pred(x) - T_true(x)|`` over the CT body points ``x`` whose true position lies in the CBCT's field
  of view (up to 20000 points); success: TRE < 2 mm. On deformed pairs ``T_true`` is the setup error alone, so the
  TRE there is shown for information only.
* Landmark error: mean ``|T_pred(x_i) - y_i|`` over up to 200 landmarks ``x_i`` (high-gradient body points in the
  70 mm cube about the isocentre) and their true CBCT positions ``y_i = T(phi(x_i))`` (the deformed, then moved,
  position); landmarks outside the field of view are dropped. ``floor``: the mean residual of the best rigid
  (least-squares) fit of the landmarks, which no rigid registration can beat. A deformed pair counts as a success
  when the landmark error is within 2 mm of its floor.
* Failure flag (network): ``RegistrationResult.flagged``; "flagged failures" counts failures flagged,
  "false alarms" successes flagged.
* Time: median wall time per case with the volumes in memory (the network's includes its confidence check); the
  ratio to elastix's median.

Printed per CT (the abdomen-pelvis CT was used in training of the shipped network and is reported separately, marked
as a training CT) and over the held-out CTs: a table per group and method; then the issue's targets checked on the
held-out CTs; then every failed case with its motion, isocentre distance and the other methods' errors.
``--results FILE`` writes the same text with the command line, the date and the machine load at the top.

Pairs are cached in ``<output-dir>/<ct>/<group>_<nnn>/`` (``case.json`` marks a finished one; a run resumes) and a
MONAI datalist per CT (``<output-dir>/<ct>/dataset.json``) lets ``monai-rigidreg evaluate`` read them too.

Usage::

    python -m benchmarks.accuracy.bench_clinical_geometry --cases-per-group 10 \\
        --results benchmarks/results/bench_clinical_geometry_2026-12-01.txt
"""

from __future__ import annotations

import argparse
import inspect
import json
import os
import sys
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np

from benchmarks.bench_common import (
    Tee,
    add_peer_mask_option,
    add_registrar_options,
    apply_registrar_options,
    checked_peers,
    ct_name,
    end_run,
    find_cts,
    fine_stage_choice_summary,
    is_training_ct,
    peer_mask,
    peer_mask_line,
    registrar_options_line,
    script_parser,
    set_threads,
    signed,
    start_run,
    training_mark,
)

REPO = Path(__file__).resolve().parents[2]

HELD_OUT_CTS = ("thorax_4dct_phase00_itkelastix.nii.gz", "head_tigre_ct.nii.gz")
REFERENCE_TRAINING_CTS = ("abdomen_pelvis_totalsegmentator_example_ct.nii.gz",)
"""A training CT run by default beside the held-out ones, for reference (every training CT is labelled as one:
:func:`~benchmarks.bench_common.is_training_ct`)."""
DEFAULT_CTS = HELD_OUT_CTS + REFERENCE_TRAINING_CTS
METHODS = ("network", "network-thorough", "network-regression", "elastix", "sitk", "elastix-roi", "ants", "greedy")
DEFAULT_METHODS = ("network", "elastix", "sitk")
GROUPS = ("small", "large", "deformed")
SUCCESS_MM = 2.0
REGRESSION_MM = 5.0  # the learned network alone's bar in clinical geometry (it leads; a polish follows)
CLINICAL_LABELS = {"small": "up to 40 mm / 30 deg", "large": "40-60 mm / 30-45 deg"}


# ---------------------------------------------------------------------------------------------------------------
# Pairs
# ---------------------------------------------------------------------------------------------------------------
def get_case(ct: Any, group: str, index: int, seed: int, folder: Path, device: str) -> tuple[Any, bool]:
    """The cached case in ``folder`` (the same seed and acquisition as now), or a new one simulated and written
    there. Returns ``(case, reused)``."""
    from monai_rigidreg.simulation.clinical import (
        CLINICAL_GROUPS,
        case_seed,
        load_clinical_case,
        make_clinical_case,
        save_clinical_case,
    )

    case = load_clinical_case(folder)
    want = case_seed(seed, ct.name, group, index)
    if case is not None and case.record.get("seed") == want and case.record.get("cbct") == current_acquisition():
        return case, True
    case = make_clinical_case(ct, CLINICAL_GROUPS[group], want, case_id=folder.name, device=device)
    save_clinical_case(case, folder, fixed=fixed_path(ct, folder.parent))
    return load_clinical_case(folder), False  # as a resumed run reads it (int16 HU): the same numbers either way


def current_acquisition() -> dict[str, Any]:
    """The clinical pairs' acquisition as a case records it (``case.json``'s ``cbct``): a cached pair with another
    one (e.g. simulated before the exposure control) is not this benchmark's pair."""
    import json

    from monai_rigidreg.simulation.clinical import ClinicalCBCTSpec

    return json.loads(json.dumps(ClinicalCBCTSpec().to_dict()))


def fixed_path(ct: Any, ct_dir: Path) -> Path:
    """The planning CT's file: the original, or a written copy when :func:`load_planning_ct` resampled it."""
    if ct.resampled_from is None and ct.path is not None:
        return ct.path
    import SimpleITK as sitk

    path = ct_dir / "fixed.nii.gz"
    if not path.is_file():
        ct_dir.mkdir(parents=True, exist_ok=True)
        sitk.WriteImage(ct.image, str(path), True)
    return path


def write_datalist(ct_dir: Path, records: list[dict[str, Any]]) -> None:
    """A MONAI datalist of the CT's cases (``monai-rigidreg evaluate --datalist`` reads it)."""
    items = []
    for r in records:
        folder = ct_dir / r["case_id"]
        items.append({k: r[k] for k in ("case_id", "group", "label", "params", "matrix", "center")}
                     | {"fixed": r["fixed"], "moving": str(folder / r["moving"]),
                        "moving_fov": str(folder / r["moving_fov"])})
    tmp = ct_dir / ".tmp-dataset.json"
    tmp.write_text(json.dumps({"test": items}, indent=1))
    tmp.replace(ct_dir / "dataset.json")


def roi_box(record: dict[str, Any]) -> tuple[float, ...]:
    """The target box ``(x0, y0, z0, x1, y1, z1)`` (CT LPS mm) of a case."""
    c = np.asarray(record["roi"]["center"], dtype=np.float64)
    h = 0.5 * np.asarray(record["roi"]["size_mm"], dtype=np.float64)
    return tuple(float(v) for v in np.concatenate([c - h, c + h]))


def roi_mask_on(image: Any, box: tuple[float, ...]) -> Any:
    """uint8 mask of a box (LPS mm) on ``image``'s grid: the voxels inside the box's index-space bounding box (exact
    for the axis-aligned grids of CTs)."""
    import SimpleITK as sitk

    from monai_rigidreg.core.geometry import Grid, transform_points

    grid = Grid.from_sitk(image)
    corners = np.array(np.meshgrid(*[[box[a], box[a + 3]] for a in range(3)], indexing="ij")).reshape(3, -1).T
    idx = transform_points(grid.physical_to_index(), corners)
    lo = np.clip(np.ceil(idx.min(0) - 1e-6).astype(int), 0, np.asarray(grid.size))
    hi = np.clip(np.floor(idx.max(0) + 1e-6).astype(int) + 1, 0, np.asarray(grid.size))
    arr = np.zeros(tuple(grid.size[::-1]), dtype=np.uint8)
    arr[lo[2]:hi[2], lo[1]:hi[1], lo[0]:hi[0]] = 1
    mask = sitk.GetImageFromArray(arr)
    mask.CopyInformation(image)
    return mask


# ---------------------------------------------------------------------------------------------------------------
# Registration
# ---------------------------------------------------------------------------------------------------------------
def run_method(method: str, ct: Any, case: Any, registrar: Any, roi_supported: bool,
               peer_mask: bool | None = None) -> dict[str, Any] | None:
    """Register one case with one method; ``None`` when the method does not apply to the case. ``peer_mask``: the
    peer tools' ``use_mask`` (``--peer-mask``)."""
    import monai_rigidreg
    from monai_rigidreg.registration.classical import register_elastix, register_sitk

    deformed = case.record["deformation"] is not None
    c = ct.center
    out: dict[str, Any] = {}
    t0 = time.perf_counter()
    if method in ("network", "network-thorough", "network-regression"):
        kwargs: dict[str, Any] = {"thorough": True} if method == "network-thorough" else {}
        if method == "network-regression":  # the learned network alone: no search, no Gauss-Newton, no last level
            kwargs["fine_stage"] = False
        elif deformed and roi_supported:
            kwargs["roi"] = roi_box(case.record)
        res = monai_rigidreg.register(ct.image, case.cbct, model=registrar, moving_fov=case.fov,
                                      resample_moving=False, **kwargs)
        params = np.asarray(res.params, dtype=np.float64)
        out.update(confidence=float(res.confidence), flagged=bool(res.flagged), roi="roi" in kwargs,
                   details=res.details, timings=dict(res.timings))
        if not np.allclose(np.asarray(res.center), c, atol=1e-3):
            from monai_rigidreg.core.geometry import recenter_params

            params = recenter_params(params, res.center, c)
    elif method == "elastix":
        params = np.asarray(register_elastix(ct.image, case.cbct, center=c, moving_mask=case.fov).params)
    elif method == "elastix-roi":
        if not deformed:
            return None
        mask = roi_mask_on(ct.image, roi_box(case.record))
        params = np.asarray(register_elastix(ct.image, case.cbct, center=c, moving_mask=mask).params)
    elif method == "sitk":
        params = np.asarray(register_sitk(ct.image, case.cbct, center=c, moving_mask=case.fov).params)
    elif method in ("ants", "greedy"):
        from monai_rigidreg.registration.peers import register_peer

        params = np.asarray(register_peer(method, ct.image, case.cbct, center=c, moving_mask=case.fov,
                                          use_mask=peer_mask).params)
    else:
        raise ValueError(method)
    out["time_s"] = time.perf_counter() - t0
    out["params"] = params
    return out


def pairs_parser(description: str, groups: list[str]) -> argparse.ArgumentParser:
    """The command line of a benchmark over the cached pairs (:func:`cached_pairs`): ``--pairs-dir``, ``--groups``
    (default ``groups``), ``--threads`` (torch threads, default 1) and ``--results`` (a file for the printed text)."""
    ap = argparse.ArgumentParser(description=description, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--pairs-dir", type=Path, default=Path("bench_out/clinical"))
    ap.add_argument("--groups", nargs="*", default=list(groups))
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--results", type=Path, default=None)
    return ap


def cached_pairs(pairs_dir: Path, groups: Any, out: Tee) -> Iterator[tuple[str, str, Any, Any]]:
    """The pairs cached in ``pairs_dir`` (``<ct>/<group>_<nnn>/``) of the given groups, each CT loaded once:
    ``(ct name, pair name, planning CT, case)``; a CT missing from the shared data, or a pair simulated with another
    acquisition than :func:`current_acquisition` (run ``bench_clinical_geometry`` on it again), is reported and
    skipped."""
    from monai_rigidreg.simulation.clinical import load_clinical_case, load_planning_ct

    acquisition = current_acquisition()
    for ct_dir in sorted(p for p in pairs_dir.iterdir() if p.is_dir()):
        paths = find_cts([ct_dir.name], out, (ct_dir.name,))
        if not paths:
            continue
        ct = load_planning_ct(paths[0])
        for case_dir in sorted(p for p in ct_dir.iterdir() if p.is_dir()):
            if case_dir.name.rsplit("_", 1)[0] not in groups:
                continue
            case = load_clinical_case(case_dir)
            if case is not None and case.record.get("cbct") != acquisition:
                out(f"skipped {ct_dir.name}/{case_dir.name}: simulated with another acquisition than the current "
                    "one (bench_clinical_geometry with this --output-dir simulates it again)")
            elif case is not None:
                yield ct_dir.name, case_dir.name, ct, case


def case_errors(pred: np.ndarray, record: dict[str, Any], points: np.ndarray) -> dict[str, float]:
    """TRE (body points in the FOV), landmark error and parameter errors of an estimate about the CT centre."""
    from monai_rigidreg.core.geometry import (
        parameter_errors,
        params_to_matrix,
        target_registration_error,
        transform_points,
    )

    c = np.asarray(record["center"])
    truth = np.asarray(record["params"])
    tre = float(target_registration_error(pred, truth, points, center=c))
    lm = np.asarray(record["landmarks"], dtype=np.float64).reshape(-1, 3)
    lm_true = np.asarray(record["landmarks_moving"], dtype=np.float64).reshape(-1, 3)
    lm_err = float(np.linalg.norm(transform_points(params_to_matrix(pred, c), lm) - lm_true, axis=1).mean()) \
        if len(lm) else float("nan")
    return {"tre": tre, "landmark": lm_err, "abs_errors": parameter_errors(pred, truth)}


def is_success(row: dict[str, Any], method: str) -> bool:
    r = row["results"][method]
    if row["deformed"]:
        floor = row["floor"] if np.isfinite(row["floor"]) else 0.0
        return bool(r["landmark"] - floor < SUCCESS_MM)
    return bool(r["tre"] < SUCCESS_MM)


# ---------------------------------------------------------------------------------------------------------------
# Report
# ---------------------------------------------------------------------------------------------------------------
def _pct(x: float) -> str:
    return f"{100 * x:.0f}%"


def _fmt(x: float) -> str:
    return "-" if x is None or not np.isfinite(x) else f"{x:.2f}"


def group_table(rows: list[dict[str, Any]], methods: list[str], out: Tee) -> None:
    """One markdown table: per group (and small+large) and method."""
    header = ["group", "method", "n", "mean TRE (mm)", "median TRE (mm)", f"success (<{SUCCESS_MM:g} mm)",
              "landmark err mean / median (mm)", "rigid floor (mm)", "flagged failures", "false alarms",
              "median time (s)", "time / elastix"]
    out("| " + " | ".join(header) + " |")
    out("|" + "---|" * len(header))
    scopes = [(g, [r for r in rows if r["group"] == g]) for g in GROUPS]
    rigid = [r for r in rows if r["group"] in ("small", "large")]
    if any(r["group"] == "large" for r in rows):
        scopes.insert(2, ("small+large", rigid))
    for gname, grows in scopes:
        if not grows:
            continue
        t_elx = float(np.median([r["results"]["elastix"]["time_s"] for r in grows])) \
            if all("elastix" in r["results"] for r in grows) else None
        for m in [*methods, "identity"]:
            sub = [r for r in grows if m in r["results"]]
            if not sub:
                continue
            res = [r["results"][m] for r in sub]
            tre = np.array([x["tre"] for x in res])
            lm = np.array([x["landmark"] for x in res])
            succ = np.array([is_success(r, m) for r in sub])
            floor = np.array([r["floor"] for r in sub])
            lm_text = f"{_fmt(np.nanmean(lm))} / {_fmt(np.nanmedian(lm))}"
            floor_text = _fmt(np.nanmean(floor)) if any(r["deformed"] for r in sub) else "-"
            if m in ("network", "network-thorough"):
                flags = np.array([bool(x["flagged"]) for x in res])
                ff = f"{int((flags & ~succ).sum())} of {int((~succ).sum())}"
                fa = f"{int((flags & succ).sum())} of {int(succ.sum())}"
            else:
                ff = fa = "-"
            if m == "identity":
                t_text, ratio = "-", "-"
            else:
                t = float(np.median([x["time_s"] for x in res]))
                t_text, ratio = f"{t:.2f}", (f"{t / t_elx:.2f}" if t_elx else "-")
            out(f"| {gname} | {m} | {len(sub)} | {_fmt(tre.mean())} | {_fmt(np.median(tre))} | "
                f"{_pct(succ.mean())} | {lm_text} | {floor_text} | {ff} | {fa} | {t_text} | {ratio} |")
    out()


def sampled_geometry(rows: list[dict[str, Any]], out: Tee) -> None:
    """What was drawn, per group: isocentre distance, |t|, largest angle, deformation peak."""
    for g in GROUPS:
        grows = [r for r in rows if r["group"] == g]
        if not grows:
            continue
        d = np.array([r["record"]["isocenter_distance_mm"] for r in grows])
        t = np.array([np.linalg.norm(r["record"]["params_isocenter"][:3]) for r in grows])
        a = np.array([np.abs(r["record"]["params_isocenter"][3:]).max() for r in grows])
        text = (f"{g} ({len(grows)}): isocentre {d.min():.0f}-{d.max():.0f} mm from the CT centre (median "
                f"{np.median(d):.0f}); |t| {t.min():.0f}-{t.max():.0f} mm; largest angle {a.min():.0f}-{a.max():.0f} "
                f"deg; TRE points per case {int(np.median([r['n_points'] for r in grows]))} (median)")
        peaks = [r["record"]["deformation_peak_mm"] for r in grows if r["deformed"]]
        if peaks:
            text += (f"; deformation peak {min(peaks):.1f}-{max(peaks):.1f} mm; landmarks per case "
                     f"{int(np.median([len(r['record']['landmarks']) for r in grows]))} (median)")
        out(f"- {text}")
    out()


def regression_targets(rows: list[dict[str, Any]], out: Tee) -> None:
    """The learned network alone (``network-regression``): the share of the rigid pairs under 5 mm TRE per band
    (targets: >= 95 % up to 40 mm / 30 degrees, >= 80 % at 40-60 mm / 30-45 degrees)."""
    out("The learned network alone (network-regression), TRE under 5 mm:")
    out()
    for group, target in (("small", 0.95), ("large", 0.80)):
        sub = [r for r in rows if r["group"] == group and "network-regression" in r["results"]]
        if sub:
            s = sum(r["results"]["network-regression"]["tre"] < REGRESSION_MM for r in sub)
            ok = "MET" if s >= target * len(sub) else "NOT MET"
            out(f"- {CLINICAL_LABELS.get(group, group)}: {s} of {len(sub)} = {_pct(s / len(sub))} "
                f"(target >= {target * 100:.0f} %): {ok}")
    out()


def targets(rows: list[dict[str, Any]], methods: list[str], out: Tee) -> None:
    """The issue's targets on the held-out CTs."""
    if "network-regression" in methods and rows:
        regression_targets(rows, out)
    if "network" not in methods or not rows:
        return
    out("Targets of issue 15 (held-out CTs, network = the default path):")
    out()

    def verdict(ok: bool) -> str:
        return "MET" if ok else "NOT MET"

    small = [r for r in rows if r["group"] == "small"]
    rigid = [r for r in rows if r["group"] in ("small", "large")]
    deformed = [r for r in rows if r["group"] == "deformed"]
    if small:
        s = sum(is_success(r, "network") for r in small)
        out(f"- up to 40 mm / 30 deg: {s} of {len(small)} under 2 mm TRE (target 100 %): {verdict(s == len(small))}")
    if rigid:
        s = sum(is_success(r, "network") for r in rigid)
        out(f"- up to 60 mm / 45 deg (small + large): {s} of {len(rigid)} = {_pct(s / len(rigid))} under 2 mm "
            f"(target >= 90 %): {verdict(s >= 0.9 * len(rigid))}")
        large = [r for r in rigid if r["group"] == "large"]
        if large:
            s = sum(is_success(r, "network") for r in large)
            out(f"  (the 40-60 mm / 30-45 deg band alone: {s} of {len(large)} = {_pct(s / len(large))})")
    allr = rigid + deformed
    if allr:
        succ = [is_success(r, "network") for r in allr]
        flags = [bool(r["results"]["network"]["flagged"]) for r in allr]
        nf = sum(1 for s in succ if not s)
        ff = sum(1 for s, f in zip(succ, flags) if not s and f)
        ns = sum(succ)
        fa = sum(1 for s, f in zip(succ, flags) if s and f)
        out(f"- every failure flagged: {ff} of {nf}: {verdict(ff == nf)}; false alarms {fa} of {ns} successes "
            f"(target <= 1 in 10): {verdict(fa <= 0.1 * ns)}")
    for ref in [m for m in ("elastix", "elastix-roi") if m in methods]:
        if deformed and all(ref in r["results"] for r in deformed):
            net = np.array([r["results"]["network"]["landmark"] for r in deformed])
            elx = np.array([r["results"][ref]["landmark"] for r in deformed])
            better = int(np.sum(net <= elx + 1e-9))
            out(f"- deformed pairs, landmark error vs {ref}: network mean {net.mean():.2f} / median "
                f"{np.median(net):.2f} mm, {ref} {elx.mean():.2f} / {np.median(elx):.2f} mm; network <= {ref} on "
                f"{better} of {len(deformed)} pairs: {verdict(net.mean() <= elx.mean())} (on the mean)")
    if "elastix" in methods and rigid:
        both = [r for r in rigid if is_success(r, "network") and is_success(r, "elastix")]
        if both:
            net = np.array([r["results"]["network"]["tre"] for r in both])
            elx = np.array([r["results"]["elastix"]["tre"] for r in both])
            out(f"- successes' TRE vs elastix on the {len(both)} rigid pairs both register: network mean "
                f"{net.mean():.2f} / median {np.median(net):.2f} mm, elastix {elx.mean():.2f} / "
                f"{np.median(elx):.2f} mm: {verdict(np.median(net) <= np.median(elx))} (on the median)")
        t_net = np.median([r["results"]["network"]["time_s"] for r in allr])
        t_elx = np.median([r["results"]["elastix"]["time_s"] for r in allr])
        out(f"- time per case (median): network {t_net:.2f} s, elastix {t_elx:.2f} s, ratio {t_net / t_elx:.2f}")
    out()


def path_summary(rows: list[dict[str, Any]], methods: list[str], out: Tee) -> None:
    """Which path the network methods took (``details["path"]``), how often the network-led path's fallback ran and
    why (``details["fallback"]``), where the fallback changed the start, and the stage medians (``timings``)."""
    for m in [m for m in ("network", "network-thorough") if m in methods]:
        res = [r["results"][m] for r in rows if m in r["results"]]
        if not res:
            continue
        paths = [x["details"].get("path", "?") for x in res]
        fell = [x for x in res if (x["details"].get("fallback") or {}).get("run")]
        reasons: dict[str, int] = {}
        for x in fell:
            for k in x["details"]["fallback"]["reasons"]:
                reasons[k] = reasons.get(k, 0) + 1
        starts: dict[str, int] = {}
        for x in res:
            starts[x["details"].get("start", "?")] = starts.get(x["details"].get("start", "?"), 0) + 1
        out(f"{m}: paths {dict((p, paths.count(p)) for p in sorted(set(paths)))}; fallback ran on {len(fell)} of "
            f"{len(res)} ({_pct(len(fell) / len(res))}; reasons {reasons}); starts {starts}")
        out("  " + fine_stage_choice_summary([x["details"].get("fine_stage_choice") for x in res]))
        checks = [x["details"]["lead_check"] for x in res if x["details"].get("lead_check")]
        if checks:  # how close the cases came to the check's limits (registration/lead.py)
            out(f"  check: confidence min {min(k['confidence'] for k in checks):.3f}, overlap min "
                f"{min(k['overlap'] for k in checks):.3f}, polish max {max(k['polish_mm'] for k in checks):.2f} mm, "
                f"translation max {max(k['max_translation_mm'] for k in checks):.1f} mm, rotation max "
                f"{max(k['max_rotation_deg'] for k in checks):.1f} deg")
        for r in rows:
            x = r["results"].get(m)
            if x is None or not x["details"].get("lead_check"):
                continue
            key = "landmark" if r["deformed"] else "tre"
            others = ", ".join(f"{k} {v[key]:.2f}" for k, v in r["results"].items() if k not in (m, "identity"))
            out(f"  - {r['ct']} {r['case_id']}: fallback {'ran' if x['details']['fallback']['run'] else 'no'}, "
                f"start {x['details'].get('start')}, {key} {x[key]:.2f}{' flagged' if x['flagged'] else ''} "
                f"({others}); check {x['details']['lead_check']}; fine-stage choice "
                f"{x['details'].get('fine_stage_choice')}")
        stages = list(dict.fromkeys(k for x in res for k in x.get("timings", {})))
        if stages:
            out("  median seconds per stage (0 where a stage did not run): " + ", ".join(
                f"{k} {np.median([x['timings'].get(k, 0.0) for x in res]):.2f}" for k in stages))
    out()


def failure_list(rows: list[dict[str, Any]], methods: list[str], out: Tee) -> None:
    """The failed cases of each method with their motion and the other methods' errors."""
    out(f"Failed cases per method (rigid groups: TRE >= {SUCCESS_MM:g} mm; deformed: landmark error >= floor + "
        f"{SUCCESS_MM:g} mm); motion = the setup error about the isocentre (mm, degrees); error = estimate - truth "
        "about the CT centre")
    out()
    for m in methods:
        sub = [r for r in rows if m in r["results"]]
        failed = [r for r in sub if not is_success(r, m)]
        out(f"{m}: {len(failed)} of {len(sub)} failed")
        for r in failed:
            res = r["results"][m]
            rec = r["record"]
            err = np.asarray(res["params"]) - np.asarray(rec["params"])
            err[3:] = (err[3:] + 180.0) % 360.0 - 180.0
            motion = signed(rec["params_isocenter"])
            key = "landmark" if r["deformed"] else "tre"
            others = ", ".join(f"{k} {v[key]:.2f}" for k, v in r["results"].items() if k not in (m, "identity"))
            conf = ""
            if "confidence" in res:
                conf = f", confidence {res['confidence']:.2f}{' flagged' if res['flagged'] else ' NOT flagged'}"
            extra = f", landmark error {res['landmark']:.2f} (floor {r['floor']:.2f})" if r["deformed"] else ""
            out(f"  - {r['ct']} {r['case_id']}: TRE {res['tre']:.2f} mm{extra} (identity "
                f"{r['results']['identity'][key]:.2f}){conf}; isocentre {rec['isocenter_distance_mm']:.0f} mm from the "
                f"CT centre; motion {motion}; error " + signed(err)
                + (f"; others ({key}): {others}" if others else ""))
    out()


# ---------------------------------------------------------------------------------------------------------------
def main() -> int:
    ap = script_parser(__doc__)
    ap.add_argument("--cts", nargs="+", default=None, metavar="CT",
                    help="CT files, or names in the data folder ($MONAI_RIGIDREG_DATA or ../shared/data); default "
                         f"{' '.join(ct_name(Path(c)) for c in DEFAULT_CTS)} (the last one is a training CT)")
    ap.add_argument("--cases-per-group", type=int, default=10, help="cases per group and CT (default 10)")
    ap.add_argument("--groups", nargs="+", default=list(GROUPS), choices=GROUPS, help="groups (default all)")
    ap.add_argument("--seed", type=int, default=1500, help="master seed of the pairs (default 1500)")
    ap.add_argument("--output-dir", type=Path, default=Path("bench_out/clinical"),
                    help="pairs in DIR/<ct>/<group>_<nnn> (resumed) (default bench_out/clinical)")
    ap.add_argument("--results", type=Path, default=None, help="also write the printed text to FILE")
    ap.add_argument("--methods", nargs="+", default=list(DEFAULT_METHODS), choices=METHODS,
                    help=f"methods (default {' '.join(DEFAULT_METHODS)}; also network-thorough, the thorough path, "
                         "network-regression, the learned network alone, elastix-roi, and the peer tools ants and "
                         "greedy)")
    ap.add_argument("--device", default="cpu", help="device of the network and the simulation (default cpu)")
    ap.add_argument("--threads", type=int, default=2, help="torch, SimpleITK and ITK/elastix threads (default 2)")
    ap.add_argument("--bundle", type=Path, default=None, help="bundle directory (default: the shipped bundle)")
    ap.add_argument("--simulate-only", action="store_true", help="build (or resume) the pairs, register nothing")
    ap.add_argument("--native-max-voxels", type=int, default=None,
                    help="the last level's grid at most this many voxels (default: the bundle's / the registrar's)")
    add_registrar_options(ap)
    add_peer_mask_option(ap)
    ap.add_argument("--no-native-level", action="store_true",
                    help="the network without its last level at native resolution (RigidRegistrar native_level)")
    ap.add_argument("--no-global-init", action="store_true",
                    help="the network without the global search (RigidRegistrar global_init)")
    args = ap.parse_args()
    if args.cases_per_group < 1 or args.threads < 1:
        ap.error("--cases-per-group and --threads must be >= 1")

    set_threads(args.threads)  # before the libraries start their pools

    import monai_rigidreg
    from monai_rigidreg.registration.classical import elastix_available
    from monai_rigidreg.registration.registrar import RigidRegistrar
    from monai_rigidreg.simulation.clinical import CLINICAL_GROUPS, ClinicalCBCTSpec, load_planning_ct, tre_points

    out = Tee()
    methods = list(dict.fromkeys(args.methods))
    if any(m.startswith("elastix") for m in methods):
        if not elastix_available():
            out("skipped methods elastix, elastix-roi: itk-elastix is not installed")
            methods = [m for m in methods if not m.startswith("elastix")]
        else:
            import itk

            itk.MultiThreaderBase.SetGlobalDefaultNumberOfThreads(args.threads)
    if args.simulate_only:
        methods = []
    roi_supported = "roi" in inspect.signature(monai_rigidreg.register).parameters

    bundle = str(args.bundle or "the shipped bundle")
    monitor, t_start = start_run(out, __spec__.name, args.threads, args.device, bundle)
    methods = checked_peers(methods, out)
    peer_mask_line(args, methods, out)
    spec = ClinicalCBCTSpec()
    out(f"methods: {' '.join(methods) or '(none: --simulate-only)'}; {args.cases_per_group} cases per group and CT, "
        f"seed {args.seed}; network roi= on deformed pairs: "
        f"{'yes' if roi_supported else 'no (register has no roi keyword)'}")
    out(f"CBCT: {spec.size[0]}x{spec.size[1]}x{spec.size[2]} at {spec.spacing:g} mm, cylindrical FOV "
        f"{spec.fov_diameter_mm:g} mm diameter x {spec.length_mm:g} mm, {spec.views} views, sod/sdd {spec.sod:g}/"
        f"{spec.sdd:g} mm, physics {json.dumps(spec.physics.to_dict())}")
    for g in args.groups:
        out(f"group {g}: {CLINICAL_GROUPS[g].describe()}")
    out()

    cts = find_cts(args.cts, out, DEFAULT_CTS)
    if not cts:
        out("no CT to benchmark")
        return 2
    registrar = (RigidRegistrar.from_bundle(args.bundle, device=args.device)
                 if {"network", "network-thorough", "network-regression"} & set(methods) else None)
    if registrar is not None:
        registrar.native_level = not args.no_native_level
        registrar.global_init = not args.no_global_init
        if args.native_max_voxels is not None:
            registrar.native_max_voxels = int(args.native_max_voxels)
        apply_registrar_options(registrar, args)
        out(registrar_options_line(registrar))
    all_rows: list[dict[str, Any]] = []
    run_notes: list[str] = []
    for path in cts:
        t0 = time.perf_counter()
        ct = load_planning_ct(path)
        note = f"{ct.name}: CT {'x'.join(map(str, ct.image.GetSize()))} at " \
               f"{'x'.join(f'{s:g}' for s in ct.image.GetSpacing())} mm"
        note += (f" (resampled from {ct.resampled_from})" if ct.resampled_from else " (native grid)")
        ct_dir = args.output_dir / ct.name
        records, rows = [], []
        t_sim = t_reg = 0.0
        n_new = 0
        for g in args.groups:
            for i in range(args.cases_per_group):
                ts = time.perf_counter()
                case, reused = get_case(ct, g, i, args.seed, ct_dir / f"{g}_{i:03d}", args.device)
                t_sim += time.perf_counter() - ts
                n_new += not reused
                records.append(case.record)
                if not methods:
                    print(f"{ct.name} {case.record['case_id']}: {'reused' if reused else 'simulated'}", flush=True)
                    continue
                rec = case.record
                m_true = np.asarray(rec["matrix"])
                points = tre_points(ct, m_true, case.fov)
                lm = np.asarray(rec["landmarks"]).reshape(-1, 3)
                row = {"ct": ct.name, "case_id": rec["case_id"], "group": g, "record": rec,
                       "deformed": rec["deformation"] is not None, "n_points": len(points),
                       "floor": float(rec["rigid_floor_mm"]) if len(lm) >= 3 else float("nan"), "results": {}}
                row["results"]["identity"] = case_errors(np.zeros(6), rec, points)
                ts = time.perf_counter()
                for m in methods:
                    res = run_method(m, ct, case, registrar, roi_supported, peer_mask(args))
                    if res is not None:
                        res.update(case_errors(res["params"], rec, points))
                        row["results"][m] = res
                t_reg += time.perf_counter() - ts
                rows.append(row)
                line = ", ".join(f"{m} {row['results'][m]['tre']:.2f}"
                                 + (f"/{row['results'][m]['landmark']:.2f}" if row["deformed"] else "")
                                 + (" F" if row["results"][m].get("flagged") else "")
                                 for m in methods if m in row["results"])
                print(f"{ct.name} {rec['case_id']} ({'reused' if reused else 'simulated'}): TRE"
                      f"{'/landmark' if row['deformed'] else ''} {line}", flush=True)
        write_datalist(ct_dir, records)
        all_rows += rows
        run_notes.append(f"{note}; {len(records)} pairs ({n_new} simulated now, {t_sim:.0f} s), registration "
                         f"{t_reg:.0f} s; {time.perf_counter() - t0:.0f} s in all; load average now "
                         f"{os.getloadavg()[0]:.2f}")
        print(run_notes[-1], flush=True)

    if methods:
        by_ct: dict[str, list[dict[str, Any]]] = {}
        for r in all_rows:
            by_ct.setdefault(r["ct"], []).append(r)
        held = [r for r in all_rows if not is_training_ct(r["ct"])]
        for name, rows in by_ct.items():
            out(f"## {name}{training_mark(name)}: {len(rows)} cases")
            out()
            group_table(rows, methods, out)
        if len({r["ct"] for r in held}) > 1:
            out(f"## all held-out CTs: {len(held)} cases")
            out()
            group_table(held, methods, out)
        out("Columns: TRE over the CT body points inside the CBCT field of view (on deformed pairs against the setup "
            "error alone: information only); success: TRE < 2 mm (deformed: landmark error < floor + 2 mm); "
            "landmark error against the true (deformed, moved) landmark positions; rigid floor: the best rigid fit "
            "of the landmarks; flags: the network's failure flag; time: median per case, volumes in memory.")
        out()
        out("Sampled geometry (all CTs):")
        out()
        sampled_geometry(all_rows, out)
        targets(held, methods, out)
        path_summary(all_rows, methods, out)
        failure_list(all_rows, methods, out)

    end_run(out, monitor, t_start, args.results, [
        *run_notes, "pairs (case.json: ground truth, isocentre, landmarks; cbct.nii.gz, cbct_fov.nii.gz) and a "
        f"datalist per CT: {args.output_dir}/<ct>/"])
    return 0


if __name__ == "__main__":
    sys.exit(main())
