"""``bench4d models``: the real track's model backends, where their weights are looked for, and whether
they are present (:mod:`methods.backends`). Weights load from a local path (each backend's environment
variable) or a hub id through the Hugging Face cache; bench4d never downloads them."""

from __future__ import annotations

import argparse


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--json", action="store_true", help="one JSON object per backend instead of the table")


def run(args: argparse.Namespace) -> int:
    import json

    from methods.backends import BACKENDS, hub_cache, locate, module_available

    rows = []
    for backend in BACKENDS:
        found = locate(backend)
        rows.append({"name": backend.name, "model": backend.model, "hub_id": backend.hub_id, "env": backend.env,
                     "size_gb": backend.size_gb, "gpu_memory_gb": backend.gpu_memory_gb,
                     "library": backend.module, "library_installed": module_available(backend.module),
                     "extra": backend.extra, "path": None if found.path is None else str(found.path),
                     "looked_in": found.source, "present": found.present})
    if args.json:
        for row in rows:
            print(json.dumps(row))
        return 0
    print(f"Hugging Face hub cache: {hub_cache()}")
    print(f"{'backend':15} {'model':38} {'size':>7} {'GPU':>6}  weights")
    for row in rows:
        where = f"{row['looked_in']}: {row['path']}" if row["path"] else row["looked_in"]
        state = "present" if row["present"] else "missing"
        library = "" if row["library_installed"] else f"; pip install 'bench4d[{row['extra']}]'"
        print(f"{row['name']:15} {row['model'][:38]:38} {row['size_gb']:5.1f}GB {row['gpu_memory_gb']:4.0f}GB  "
              f"{state} ({where}){library}")
        if row["hub_id"]:
            print(f"{'':15} hub id {row['hub_id']}, or a local folder in ${row['env']}")
    return 0
