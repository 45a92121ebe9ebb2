"""A model soup: the mean of several oidn_ft runs' weights (python soup.py OUT RUNS_A RUNS_B ...; each RUNS
holds oidn_ft_rt_hdr_alb_nrm/), written as OUT/oidn_ft_rt_hdr_alb_nrm/ for the evaluator."""
import json
import sys
from pathlib import Path

from safetensors.torch import load_file, save_file

RUN = "oidn_ft_rt_hdr_alb_nrm"
out, ins = Path(sys.argv[1]) / RUN, [Path(p) / RUN for p in sys.argv[2:]]
out.mkdir(parents=True, exist_ok=True)
states = [load_file(str(p / "model.safetensors")) for p in ins]
save_file({k: sum(s[k] for s in states) / len(states) for k in states[0]}, str(out / "model.safetensors"))
record = json.loads((ins[0] / "model.json").read_text())
record["soup_of"] = [str(p) for p in ins]
(out / "model.json").write_text(json.dumps(record, indent=1))
print(f"soup of {len(states)} runs -> {out}")
