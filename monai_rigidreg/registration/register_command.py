"""``monai-rigidreg register``: register a CBCT (moving) to a planning CT (fixed).

Writes DIR/transform.tfm (ITK Euler3DTransform, fixed->moving, readable by 3D Slicer, ITK and SimpleITK;
--transform-format h5 for transform.h5), DIR/TransformParameters.txt (the same for elastix's transformix),
DIR/registered.nii.gz (the CBCT on the CT grid), DIR/result.json (parameters, couch shifts in IEC 61217 terms,
confidence, audit trail), DIR/qc.png and, when both inputs are DICOM series with their own frames of reference,
DIR/registration.dcm (a DICOM Spatial Registration object).
"""

from __future__ import annotations

import argparse
import json
import logging
from pathlib import Path
from typing import Any

from monai_rigidreg.core.command_text import add_command, outputs_listing

__all__ = ["add_parser", "run"]


def add_parser(subparsers: argparse._SubParsersAction) -> argparse.ArgumentParser:
    """Add the ``register`` sub-command to ``subparsers`` (``monai-rigidreg``'s); it sets ``func=run``."""
    p = add_command(subparsers, "register", __doc__, run)
    p.add_argument("--fixed", type=Path, default=None, help="planning CT: NIfTI, MHA, NRRD or a DICOM folder")
    p.add_argument("--moving", type=Path, default=None, help="CBCT: NIfTI, MHA, NRRD or a DICOM folder")
    p.add_argument("--datalist", type=Path, default=None,
                   help="instead of --fixed/--moving: a JSON list of {\"fixed\", \"moving\"} pairs (paths relative to "
                   "the file's folder) registered in one process with the network loaded once; each pair's outputs "
                   "go to OUTPUT_DIR/<case_id>; a failing pair is reported and skipped (exit status 2 at the end)")
    p.add_argument("--output-dir", required=True, type=Path, metavar="DIR",
                   help="where the outputs go (refused where it exists and is not empty, unless --overwrite)")
    p.add_argument("--refine", action="store_true", help="polish with SimpleITK Mattes MI (masked to the CBCT FOV)")
    p.add_argument("--device", default="auto", help="auto | cpu | cuda | cuda:N")
    p.add_argument("--threads", type=int, default=None, metavar="N",
                   help="CPU threads for torch and SimpleITK (default: one per core, less the cores other work keeps "
                        "busy as each registration starts; 1 on a machine busy with other work)")
    p.add_argument("--bundle", type=Path, default=None, help="MONAI bundle directory (default: the shipped one)")
    p.add_argument("--cascade-steps", type=int, default=None, help="network applications (default: bundle's)")
    p.add_argument("--fixed-series-uid", default=None, help="DICOM series UID of the CT (default: largest)")
    p.add_argument("--moving-series-uid", default=None, help="DICOM series UID of the CBCT (default: largest)")
    p.add_argument("--no-qc", action="store_true", help="skip the QC figure")
    p.add_argument("--overwrite", action="store_true", help="replace an existing output directory")
    p.add_argument("--isocenter", default=None, metavar="X,Y,Z",
                   help="plan isocentre in CT coordinates (LPS mm) for the couch shifts (default: the CBCT centre)")
    p.add_argument("--patient-position", default=None, metavar="POS",
                   help="DICOM Patient Position of the CT for the couch shifts (HFS, HFP, FFS, FFP, HFDL, HFDR, FFDL, "
                   "FFDR; default: the CT's DICOM header, else HFS assumed with a warning)")
    p.add_argument("--reg", choices=("auto", "on", "off"), default="auto",
                   help="write registration.dcm: auto (when both inputs are DICOM series with their own frames of "
                   "reference; otherwise a warning says why not), on (required: refused before registering when it "
                   "cannot be written), off")
    p.add_argument("--no-fine-stage", action="store_true",
                   help="the learned network alone: the regression's estimate without the Gauss-Newton stage (to "
                   "measure it; with --refine the optimizer still runs)")
    p.add_argument("--no-global-init", action="store_true",
                   help="skip the global search for large offsets (on by default: translations over +-72 mm for "
                   "27 rotation candidates; the network also starts from its best candidates where they disagree)")
    p.add_argument("--roi", default=None, metavar="X0,Y0,Z0,X1,Y1,Z1|MASK",
                   help="match only this region of the CT (clip box): a box in CT LPS mm, or a mask image on the CT's "
                   "physical space (non-zero inside)")
    p.add_argument("--match", choices=("soft", "bone"), default="soft",
                   help="soft: all tissue (default); bone: the CT's bone and a few mm around it")
    p.add_argument("--no-native-level", action="store_true",
                   help="skip the last Gauss-Newton steps over the whole CBCT field of view at the inputs' resolution "
                   "(on by default; docs/usage.md says what it changes)")
    p.add_argument("--thorough", action="store_true",
                   help="the thorough path on every pair: the global search, further starts and the swapped-input "
                   "confidence check always (by default the network leads: its estimate, the last level and a cheap "
                   "check, the rest only where the check fails)")
    p.add_argument("--keep-couch", action="store_true",
                   help="keep the couches in the match (by default the CT's tissue outside its body, the couch, "
                   "counts as air and carries no match weight, so the treatment couch in the CBCT meets none either: "
                   "couches do not move with the patient)")
    p.add_argument("--transform-format", choices=("tfm", "h5"), default="tfm",
                   help="ITK transform file: transform.tfm (text) or transform.h5 (HDF5)")
    p.add_argument("--json", action="store_true",
                   help="print one JSON object on stdout and nothing else (the log goes to stderr): result.json's "
                   "record and 'outputs', the files written by name; with --datalist the batch summary")
    p.add_argument("--fail-on-flag", action="store_true",
                   help="exit with status 3 when the result is flagged as a likely failure (default: 0; the outputs "
                   "are written either way and result.json says flagged and why: details.flag_reasons)")
    p.add_argument("--allow-swapped", action="store_true",
                   help="the fixed image really is the planning CT although it looks like the CBCT (its box inside "
                   "the moving one's, or a CBCT's cylindrical field of view): keep the warning, do not flag the "
                   "result for it (default: flagged, details.signals.swapped)")
    p.add_argument("--allow-other-patient", action="store_true",
                   help="register DICOM inputs whose headers name different patients (Patient ID, Issuer of "
                   "Patient ID), e.g. a phantom or series pseudonymised apart; the warning is kept in result.json "
                   "(default: refused before registering, exit status 2)")
    return p


def run(args: argparse.Namespace) -> int:
    if args.datalist is not None:
        return _run_pairs(args)
    # one pair: its two files are read while the registration stack (torch: about 0.9 s) is imported; a read the
    # run did not take (it failed first) is dropped with its image
    from monai_rigidreg.io.prefetch import drop_prefetched, prefetch_volumes

    try:
        prefetch_volumes([args.fixed, args.moving])
    except RuntimeError as exc:  # no thread to read in (a process limit): load_volume reads them itself
        logging.getLogger(__name__).debug("inputs not read ahead: %s", exc)
    try:
        return _run_pairs(args)
    finally:
        drop_prefetched([args.fixed, args.moving])


def _run_pairs(args: argparse.Namespace) -> int:
    """:func:`run` once its inputs' reads are started: the batch (``--datalist``) or the one pair."""
    # imported here, not at the top: `monai-rigidreg --help` imports every sub-command module to build its parser,
    # and the registration stack pulls in torch and the networks (python -c "import
    # monai_rigidreg.registration.registrar")
    from monai_rigidreg.registration.files import register_files
    from monai_rigidreg.registration.inputs import check_register_inputs
    from monai_rigidreg.registration.registrar import RigidRegistrar

    if args.datalist is not None:
        from monai_rigidreg.registration.pairs import RegistrationEvaluator, registration_pairs  # and tqdm: batch only

        return _run_batch(args, RigidRegistrar, RegistrationEvaluator, registration_pairs)

    # inputs, options and the output folder before the network is loaded (register_files checks them again, cheaply)
    check_register_inputs(args.fixed, args.moving, args.output_dir, args.overwrite, args.cascade_steps)
    options = _match_options(args)
    registrar = _load_registrar(args, RigidRegistrar)
    paths = register_files(registrar, args.fixed, args.moving, args.output_dir, refine=args.refine,
                           overwrite=args.overwrite, qc=not args.no_qc, cascade_steps=args.cascade_steps,
                           fixed_series_uid=args.fixed_series_uid, moving_series_uid=args.moving_series_uid,
                           isocenter=args.isocenter, reg=args.reg, transform_format=args.transform_format,
                           fine_stage=False if args.no_fine_stage else None, patient_position=args.patient_position,
                           **options)
    summary = json.loads(paths["result.json"].read_text())
    code = 3 if args.fail_on_flag and summary["flagged"] else 0  # 3: cli.EXIT_FLAGGED
    if getattr(args, "json", False):  # machine-readable: the whole record and where the files are, nothing else
        print(json.dumps({**summary, "outputs": {name: str(p) for name, p in paths.items()}}, indent=2))
        return code
    couch = summary.get("couch_shift", {})
    confidence = summary["confidence"]  # null in result.json where the check did not run
    print(json.dumps({"params": summary["params"], "confidence": None if confidence is None else round(confidence, 2),
                      "confidence_meaning": summary.get("confidence_meaning"),
                      "flagged": summary["flagged"],
                      "flag_reasons": (summary.get("details") or {}).get("flag_reasons") or [],
                      "runtime_s": summary["runtime_s"],
                      "couch_shift_6dof": {k: round(v, 2) for k, v in couch.get("6dof", {}).items()},
                      "couch_shift_3dof": {k: round(v, 2) for k, v in couch.get("3dof", {}).items()},
                      "couch_patient_position": couch.get("patient_position"),
                      "couch_isocentre": couch.get("isocentre_source")}, indent=2))
    print(outputs_listing(paths))
    return code


def _load_registrar(args: argparse.Namespace, registrar_cls: Any) -> Any:
    """The bundle's registrar on ``--device``, with ``--no-native-level`` and ``--thorough`` applied."""
    from monai_rigidreg.core.device import set_cpu_threads

    set_cpu_threads(args.threads)
    registrar = registrar_cls.from_bundle(args.bundle, device=args.device)
    registrar.native_level = registrar.native_level and not args.no_native_level
    registrar.network_leads = registrar.network_leads and not args.thorough
    registrar.adapt_threads = args.threads is None  # --threads N: exactly N
    return registrar


def _match_options(args: argparse.Namespace) -> dict[str, Any]:
    """``global_init``, ``roi`` (checked: a bad box or mask ends the run before the network is loaded), ``match`` and
    ``keep_couch``."""
    from monai_rigidreg.registration.match_region import parse_roi

    return {"global_init": False if args.no_global_init else None, "roi": parse_roi(args.roi), "match": args.match,
            "keep_couch": args.keep_couch, "allow_swapped": args.allow_swapped,
            "allow_other_patient": args.allow_other_patient}


def _run_batch(args: argparse.Namespace, registrar_cls: Any, evaluator_cls: Any, pairs_fn: Any) -> int:
    """``register --datalist``: every pair with one loaded network; prints pairs per second and what failed."""
    from monai_rigidreg.core.errors import InputError
    from monai_rigidreg.io.volumes import check_output_dir

    if args.fixed is not None or args.moving is not None:
        raise InputError("give either --fixed/--moving (one pair) or --datalist (pairs), not both")
    pairs = pairs_fn(datalist=args.datalist, dataset_dir=args.datalist.parent)
    check_output_dir(args.output_dir, args.overwrite, allow_existing=True)
    options = _match_options(args)
    registrar = _load_registrar(args, registrar_cls)
    evaluator = evaluator_cls(registrar, pairs, args.output_dir, refine=args.refine, overwrite=args.overwrite,
                              qc=not args.no_qc, fine_stage=False if args.no_fine_stage else None,
                              isocenter=args.isocenter, reg=args.reg, transform_format=args.transform_format,
                              patient_position=args.patient_position, **options)
    summary = evaluator.run()  # BatchFailures (exit status 2) names the pairs that failed
    print(json.dumps(summary, indent=2))
    return 0
