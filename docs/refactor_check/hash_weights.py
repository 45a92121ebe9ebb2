"""A sha256 per weights file under a runs folder: for safetensors of the tensors (sorted names and their
bytes, not the metadata, whose history holds wall-clock seconds), for .tza of the file. Packs are left out."""
import hashlib
import sys
from pathlib import Path

from safetensors import safe_open


def digest(path: Path) -> str:
    h = hashlib.sha256()
    if path.suffix == ".tza":
        h.update(path.read_bytes())
        return h.hexdigest()
    with safe_open(str(path), framework="pt") as f:
        for k in sorted(f.keys()):
            h.update(k.encode() + f.get_tensor(k).contiguous().numpy().tobytes())
    return h.hexdigest()


if __name__ == "__main__":
    root = Path(sys.argv[1])
    for path in sorted(p for p in root.rglob("*") if p.suffix in (".safetensors", ".tza") and "pack" not in p.parts):
        print(digest(path), path.relative_to(root))
