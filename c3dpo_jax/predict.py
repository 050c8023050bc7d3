"""Command line: 2D keypoints in a file -> 3D reconstructions out.

  c3dpo-predict --workdir=runs/synthetic --input=poses.json --output=out.npz [--figures=DIR]
      [--refine_iters=0] [--refine_prior=W] [--turns=T] [--turn_span=circle]
      [--one_handedness] [--handedness_reference=h36m|coco|BODY.npy|BODY.json|BODY.txt|BODY.csv]
      [--handedness_body=BODY.npy] [--noreplace_keypoints_with_input]

(or ``python -m c3dpo_jax.predict ...``). Every inference option (``lift.InferenceConfig``)
is a flag of the same name; unset, the model's own. Errors in the input print as one line
``error: ...`` (exit status 2); ``--verbose`` keeps the traceback.

Input: the release's JSON format (a list of entries with ``kp_loc`` 2 x N and
``kp_vis``, or ``{"dataset", "data"}``), or COCO-style keypoint annotations
(``{"annotations": [{"keypoints": [x, y, v] * N, ...}]}``, visible where v >= 1).
Entries or annotations with no visible point are skipped with a warning (``index`` in the
output says which input each reconstruction is).
Pictures (``--figures``): the skeleton is ``--skeleton`` (a name such as ``h36m``, or
index pairs ``0-1,1-2``), else the input file's, else the training data's; the up direction
is ``--y_up``/``--noy_up``, else the input file's, else image convention (y down) for a
COCO file and the training data's for the release's format.
Output: ``.npz`` (arrays ``shape_3d (M, N, 3)``, ``shape_canonical``, ``rotation``,
``alpha``, ``kp_reprojected``, ``index`` (M,) = position in the input) or ``.json``
(a list with one dict of nested lists per reconstructed sample).
"""

import dataclasses
import json
import os

import numpy as np
from absl import flags, logging

from c3dpo_jax import cli
from c3dpo_jax.lift import InferenceConfig
from c3dpo_jax.reconstruct import Reconstruction, load, reconstruct

_SUFFIXES = (".json", ".npz")


def _define_flags() -> dict:
    """Defined only when run as a script, so that importing never clashes with main's flags."""
    return {
        "workdir": flags.DEFINE_string("workdir", None, "Trained workdir or its step dir."),
        "input_path": flags.DEFINE_string("input", None, "Release JSON or COCO annotations."),
        "output": flags.DEFINE_string("output", None, "Reconstructions file (.json/.npz)."),
        "figures": flags.DEFINE_string("figures", None, "Optional directory for a few pictures."),
        "n_figures": flags.DEFINE_integer("n_figures", 3, "Samples to draw with --figures."),
        "skeleton": flags.DEFINE_string(
            "skeleton", None, "Lines for the pictures: a built-in name (h36m, coco, cub_birds, "
            "...) or index pairs such as 0-1,1-2,2-3 (default: the input's or the training "
            "data's)."),
        "y_up": flags.DEFINE_bool(
            "y_up", None, "Pictures: the input's y axis points up (motion capture) rather than "
            "down (image pixels) (default: the input's or the training data's setting)."),
        **_inference_flags(),
        "verbose": flags.DEFINE_bool("verbose", False, "Show the traceback of input errors."),
    }


# The flags of the inference options, by the type of their ``InferenceConfig`` field; a
# body (a tuple of rows) is a file's name.
_DEFINE = {int: flags.DEFINE_integer, float: flags.DEFINE_float, bool: flags.DEFINE_bool,
           str: flags.DEFINE_string, tuple: flags.DEFINE_string}
_INFERENCE_HELP = {
    "refine_iters": "Levenberg-Marquardt steps refining each view's camera and shape "
                    "coefficients (0: Phi's own output, the release's single pass).",
    "refine_prior": "Weight of the refinement's prior (the canonical shape's squared distance "
                    "to Phi's).",
    "refine_handedness": "Weight of the refinement's term that keeps each view's handedness "
                         "evidence against the model's mean shape at least Phi's or "
                         "--refine_handedness_margin, whichever is lower (0: none).",
    "refine_handedness_margin": "The evidence below which that term charges a fall (1: any).",
    "turns": "Copies of each view turned in-plane whose median depth is kept (1: one pass).",
    "turn_span": "Where the copies are turned: augmentation, circle or circle_and_range.",
    "one_handedness": "Give every view the handedness of --handedness_reference (a view and "
                      "its depth mirror image fit the same 2D points; a model may lift some "
                      "views one way and the rest the other).",
    "handedness_reference": "What the handedness is taken from: 'mean_shape' (the model's, "
                            "which may itself be mirrored), a body of the model's joint order, "
                            "'h36m' (Human3.6M's 17 joints) or 'coco' (COCO's 17 person "
                            "keypoints), or a file of one 3D example of the points in the "
                            "model's order (.npy, .json, .txt, .csv: N rows of x, y, z, any "
                            "pose, orientation and scale), or 'views_mean' (the training "
                            "views' mean shape, stored with a model trained with it); a body "
                            "turns --one_handedness on, "
                            "and with --noone_handedness it mirrors every view or none, as the "
                            "model's mean shape is the body's mirror image or not.",
    "handedness_body": "A file of one 3D example of the points, as --handedness_reference "
                       "takes one (the reference 'body').",
    "handedness_evidence": "How --one_handedness weighs a view against the reference: "
                           "'procrustes' (the whole shape) or 'tetrahedra' (the chirality of "
                           "each point's corner with its three nearest points).",
    "handedness_from_output": "--one_handedness weighs each view's output (the input's x, y "
                              "with the model's depth) instead of its canonical shape.",
    "replace_keypoints_with_input": "The 3D output's x, y at visible points are the input "
                                    "itself (--noreplace_keypoints_with_input: the "
                                    "reprojection).",
}


def _inference_flags() -> dict:
    """One flag per ``InferenceConfig`` field, of its name (None: the model's setting)."""
    return {f.name: _DEFINE[f.type](f.name, None, _INFERENCE_HELP[f.name] + " Default: the "
                                    "model's setting.")
            for f in dataclasses.fields(InferenceConfig)}


def read_coco(obj: dict) -> dict[str, np.ndarray]:
    """COCO keypoint annotations -> ``kp (M, N, 2)``, ``vis (M, N)``, ``index (M,)``: those
    with a visible point (``importers.read_coco``, the package's one COCO reader)."""
    from c3dpo_jax.data import importers

    data, index = importers.read_coco(obj)
    return {"kp": data.kp, "vis": data.vis, "index": index}


def read_input(path: str) -> dict[str, np.ndarray]:
    """Either input format -> ``kp``, ``vis``, ``index`` (+ ``class_mask``, ``K``, ``kp3d``)."""
    from c3dpo_jax.data import importers, json_dataset

    obj = json_dataset.read_json(path)

    if isinstance(obj, dict) and "annotations" in obj:
        out = read_coco(obj)
        style = {"y_up": False, "unit": "px", "skeleton": importers.coco_skeleton(obj)}
        out["style"] = {k: v for k, v in style.items() if v is not None}
        return out
    # One visible point is enough to lift (reconstruct accepts it); training needs two.
    # Entries with none are skipped, as COCO annotations are; other faults are errors.
    data = json_dataset.parse(obj, name=os.path.basename(path).removesuffix(".json"),
                              min_visible=0, kp_dtype=np.float64)  # exact far from 0
    seen = data.vis.sum(1) > 0
    index = np.flatnonzero(seen)
    if not seen.all():
        if not seen.any():
            raise ValueError(f"{path}: no entry has a visible point")
        importers.warn_skipped(path, np.flatnonzero(~seen), len(data), "entries",
                               "no visible point")
        data = data.subset(index)
    out = {"kp": data.kp, "vis": data.vis, "index": index}
    optional = (("class_mask", data.class_mask), ("K", data.intrinsics), ("kp3d", data.kp3d))
    for name, value in optional:
        if value is not None:
            out[name] = value
    if isinstance(obj, dict):
        out["style"] = {k: obj[k] for k in ("skeleton", "y_up", "unit") if obj.get(k) is not None}
    return out


def _check_output(path: str) -> None:
    """The output's suffix picks its format."""
    if not path.endswith(_SUFFIXES):
        raise ValueError(f"--output must end in .json or .npz, got {path!r}")


def write_output(rec: Reconstruction, index: np.ndarray, path: str) -> None:
    """Writes ``.npz`` or ``.json`` (module docstring), making the parent directory."""
    _check_output(path)
    os.makedirs(os.path.dirname(path) or ".", exist_ok=True)
    arrays = dict(rec._asdict(), index=index)
    if path.endswith(".npz"):
        np.savez(path, **arrays)
    elif path.endswith(".json"):
        rows = [{k: v[i].tolist() for k, v in arrays.items()} for i in range(len(index))]
        with open(path, "w") as f:
            json.dump(rows, f)


def picture_style(workdir: str, inputs: dict, skeleton=None, y_up: bool | None = None
                  ) -> tuple[list[tuple[int, int]], bool, str]:
    """(skeleton pairs, y_up, unit) for pictures of ``inputs``: the arguments, else the
    input file's settings, else the training data's (``visualise.run_style``)."""
    from c3dpo_jax import run_config, skeletons, visualise

    given = {"skeleton": skeleton, "y_up": y_up}
    style = dict(inputs.get("style", {}), **{k: v for k, v in given.items() if v is not None})
    if not visualise.STYLE_DEFAULTS.keys() <= style.keys():
        if not os.path.exists(os.path.join(workdir, run_config.CONFIG_FILE)):  # a step dir
            workdir = os.path.dirname(os.path.dirname(os.path.abspath(workdir)))
        style = {**visualise.run_style(run_config.load_config(workdir) or {}), **style}
    return (skeletons.skeleton(style.get("skeleton"), inputs["kp"].shape[1]),
            bool(style.get("y_up", False)), style.get("unit") or "")


def _figures(rec, inputs, out_dir: str, n: int, edges, y_up: bool, unit: str) -> None:
    from c3dpo_jax import visualise

    visualise.write_reconstruction_figures(
        rec, inputs["kp"], inputs["vis"], out_dir, gt=inputs.get("kp3d"), n=n, edges=edges,
        y_up=y_up, unit=unit, titles=[f"sample {i}" for i in inputs["index"]])


def _check_figures(figures: str | None, n_figures: int, skeleton, y_up) -> None:
    """The picture flags make sense together, before any work."""
    if not figures:
        if skeleton is not None or y_up is not None:
            logging.warning("--skeleton and --y_up shape the pictures only: give --figures=DIR "
                            "to draw them")
        return
    if n_figures < 1:
        raise ValueError(f"--n_figures={n_figures} (must be >= 1 with --figures)")
    if os.path.exists(figures) and not os.path.isdir(figures):
        raise ValueError(f"--figures={figures!r} is a file; it names a directory for the "
                         "pictures")


def run(workdir: str, input_path: str, output: str, figures: str | None = None,
        n_figures: int = 3, skeleton: str | None = None, y_up: bool | None = None,
        **options) -> Reconstruction:
    """What the command line does; returns the reconstructions it wrote. ``options``:
    ``reconstruct``'s inference options (None: the model's)."""
    _check_output(output)  # before the work, not after it
    _check_figures(figures, n_figures, skeleton, y_up)
    params = load(workdir)
    inputs = read_input(input_path)
    if figures:  # a bad --skeleton fails before the work too
        edges, y_up, unit = picture_style(workdir, inputs, skeleton, y_up)
    perspective = params.config.projection_type == "perspective"
    K = inputs.get("K") if perspective else None
    if not perspective and inputs.get("K") is not None:
        logging.warning("%s holds intrinsics (K); %s is an orthographic model, which ignores "
                        "them", input_path, workdir)
    if perspective and K is None:
        raise ValueError(f"{workdir} is a perspective model: each input needs its intrinsics, "
                         "a 'K' field (3 x 3) in every entry of the release's JSON format "
                         "(COCO annotations have none)")
    rec = reconstruct(params, inputs["kp"], inputs["vis"], K=K, class_mask=inputs.get("class_mask"),
                      **options)
    write_output(rec, inputs["index"], output)
    logging.info("wrote %d reconstructions to %s", len(inputs["index"]), output)
    if figures:
        _figures(rec, inputs, figures, n_figures, edges, y_up, unit)
    return rec


def cli_main():
    """The ``c3dpo-predict`` console script."""
    holders = _define_flags()
    verbose = holders.pop("verbose")
    flags.mark_flags_as_required(["workdir", "input", "output"])

    def _main(argv):
        del argv
        cli.setup_logging()
        run(**{name: holder.value for name, holder in holders.items()})

    cli.run(_main, verbose)


if __name__ == "__main__":
    cli_main()
