"""mcdenoise: the one name the project installs under.

The card's folders stay at the top of the repository (``pipeline/``, ``render/``, ``clean/``,
``train/``, ``evaluate/``); an installed wheel holds them as ``mcdenoise.pipeline``,
``mcdenoise.render``, … (pyproject.toml maps them with setuptools' ``package-dir``), so nothing
generic lands in a user's site-packages (a top-level ``evaluate`` would shadow Hugging Face's).
Every project import names them that way (``from mcdenoise.pipeline.config import …``).

In a source checkout those folders sit beside this one, not inside it: there the package's search
path also holds the repository root, so ``mcdenoise.pipeline`` is ``./pipeline`` and
``python -m pipeline …`` from the root runs the same modules as the installed ``mcdenoise``
command. An installed package has them inside and leaves its path alone.
"""
from pathlib import Path

_HERE = Path(__file__).resolve().parent
# A source checkout: the folders are this one's siblings (an installed package holds them inside).
if not (_HERE / "pipeline").is_dir() and (_HERE.parent / "pipeline" / "__init__.py").is_file():
    __path__.append(str(_HERE.parent))
