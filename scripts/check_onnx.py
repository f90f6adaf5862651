#!/usr/bin/env python3
"""Interop check of gangway's ONNX models.

For every reference file written by `cargo test --test it onnx_reference::` (two JSON
per model under models/ and for the desire lines that test trains, a batch and one row, since tract runs one row through
its own plan when the weights are float16: the model path, fixed inputs and
tract's outputs), this
runs the official `onnx` checker on the model and runs it in onnxruntime on the
same inputs; outputs must agree with tract within 1e-4.

Usage: python scripts/check_onnx.py REFERENCE_DIR
"""
import json
import pathlib
import sys

import numpy as np
import onnx
import onnxruntime as ort

TOLERANCE = 1e-4
REQUIRED_METADATA = {
    "gangway.kind", "gangway.version", "gangway.site", "gangway.grid",
    "gangway.map_hash", "gangway.classes", "gangway.iterations", "gangway.seed",
}


def check(reference_path: pathlib.Path) -> str | None:
    """Returns None when the model passes, else why it failed."""
    ref = json.loads(reference_path.read_text())
    model = onnx.load(ref["model"])
    onnx.checker.check_model(model, full_check=True)
    opset = max(o.version for o in model.opset_import if o.domain in ("", "ai.onnx"))
    if opset < 13:
        return f"opset {opset} < 13"
    keys = {p.key for p in model.metadata_props}
    if REQUIRED_METADATA - keys:
        return f"missing metadata {sorted(REQUIRED_METADATA - keys)}"
    session = ort.InferenceSession(ref["model"], providers=["CPUExecutionProvider"])
    feeds = {
        i["name"]: np.asarray(i["data"], dtype=np.float32).reshape(i["shape"])
        for i in ref["inputs"]
    }
    (got,) = session.run([ref["output"]["name"]], feeds)
    want = np.asarray(ref["output"]["data"], dtype=np.float32).reshape(ref["output"]["shape"])
    if got.shape != want.shape:
        return f"shape {got.shape} vs tract {want.shape}"
    diff = float(np.max(np.abs(got - want)))
    print(f"  {reference_path.name} ({ref['model']}): opset {opset}, max |onnxruntime - tract| = {diff:.2e}")
    return None if diff <= TOLERANCE else f"max difference {diff:.2e} > {TOLERANCE}"


def main() -> int:
    if len(sys.argv) != 2:
        print(__doc__, file=sys.stderr)
        return 2
    refs = sorted(pathlib.Path(sys.argv[1]).glob("*.json"))
    if not refs:
        print(f"no reference files in {sys.argv[1]}; run `cargo test --test it onnx_reference::` first",
              file=sys.stderr)
        return 2
    failed = 0
    for ref in refs:
        try:
            problem = check(ref)
        except Exception as e:  # a checker or runtime error is a failure of that model
            problem = f"{type(e).__name__}: {e}"
        if problem:
            failed += 1
            print(f"FAIL {ref.name}: {problem}")
    print(f"{len(refs) - failed} passed, {failed} failed")
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())
