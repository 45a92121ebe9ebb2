"""The paragraph on top of ``eval.md``, generated from the numbers (``compare.annotate``'s leads).

For the in-distribution group (the first one, ``eval.split``) and each spp: which denoiser has
the best mean on each metric and whether its lead over the runner-up is significant (the paired
bootstrap 95 % interval of their per-frame difference excludes 0); where plain MC at equal time
beats every denoiser on PSNR; which methods are not available at which spp. For the hard-case
groups (stress presets, external scenes) the same leaders in a compact form (``*`` marks a
significant lead). The noisy input and equal-time MC rows are never "the best denoiser"; methods
with the leader's scores on every frame (a model that returns another method's output) are named
with it, not as its runner-up.
"""
from __future__ import annotations

from .scoring import METRICS


def _join(items: list[str]) -> str:
    return items[0] if len(items) == 1 else ", ".join(items[:-1]) + " and " + items[-1]


def _margin(lead: dict) -> str:
    if lead.get("runner_up") is None:
        return "the only denoiser"
    if lead.get("lo") is None:
        why = f"{lead['n']} paired frames" if lead.get("diff") is not None else "non-finite values (PSNR inf)"
        return f"ahead of `{lead['runner_up']}`, untested: {why}"
    how = "significantly" if lead["significant"] else "not significantly"
    return f"{how} ahead of `{lead['runner_up']}`"


def _prose(metric: str) -> str:
    """"PSNR" for the column "PSNR dB": units read badly in a sentence."""
    return METRICS[metric].column.split(" ")[0]


def leader_phrases(leads: dict, metric_names: list[str]) -> list[str]:
    """"`oidn` on L1 and PSNR (significantly ahead of `isik`)", one phrase per leader, metrics
    with the same runner-up and verdict merged, in metric order."""
    by_best: dict[str, dict[str, list[str]]] = {}
    for m in metric_names:
        lead = leads.get(m)
        if lead:
            by_best.setdefault(_leader(lead), {}).setdefault(_margin(lead), []).append(_prose(m))
    return [f"{best} on " + ", on ".join(f"{_join(cols)} ({margin})" for margin, cols in margins.items())
            for best, margins in by_best.items()]


def _leader(lead: dict, compact: bool = False) -> str:
    """"`ours`", or with the methods whose scores are the same on every frame, in name order:
    "`oidn` (identical scores: `ours`)", compact "`oidn`=`ours`"."""
    if not lead.get("tied"):
        return f"`{lead['best']}`"
    first, *same = [f"`{n}`" for n in sorted([lead["best"], *lead["tied"]])]   # one name per group
    return "=".join([first, *same]) if compact else f"{first} (identical scores: {_join(same)})"


def mc_clause(entry: dict) -> str | None:
    """Equal-time MC rows whose mean PSNR beats every denoiser's, if any."""
    lead = entry.get("leads", {}).get("psnr")
    if not lead:
        return None
    beat = [n for n, et in entry.get("equal_time", {}).items()
            if et.get("metrics", {}).get("psnr") is not None and et["metrics"]["psnr"] > lead["mean"]]
    if not beat:
        return None
    return f"plain MC at equal time to {_join([f'`{n}`' for n in beat])} has a higher PSNR than every denoiser"


def spp_sentence(spp: str, entry: dict, metric_names: list[str]) -> str:
    if "skipped" in entry:
        return f"At {spp} spp: not evaluated ({entry['skipped']})."
    phrases = leader_phrases(entry.get("leads", {}), metric_names)
    text = f"At {spp} spp the best denoiser is " + "; ".join(phrases) if phrases else \
        f"At {spp} spp no denoiser was scored"
    extra = [c for c in (mc_clause(entry),) if c]
    missing = [n for n, r in entry["methods"].items() if not r["available"]]
    if missing:
        extra.append(f"not available: {_join([f'`{n}`' for n in missing])} (reasons in the table)")
    return text + "".join(f"; {c}" for c in extra) + "."


def compact_leaders(leads: dict, metric_names: list[str]) -> str:
    """"`oidn` on L1*, SSIM; `isik` on PSNR*": leaders with their metrics, * for a significant lead."""
    by_best: dict[str, list[str]] = {}
    for m in metric_names:
        lead = leads.get(m)
        if lead:
            by_best.setdefault(_leader(lead, compact=True), []).append(_prose(m) + ("*" if lead.get("significant") else ""))
    return "; ".join(f"{best} on {', '.join(ms)}" for best, ms in by_best.items())


def hard_clause(group: str, g: dict, metric_names: list[str]) -> str:
    parts = [f"{spp} spp: {compact_leaders(entry['leads'], metric_names)}." for spp, entry in g["spp"].items()
             if "skipped" not in entry and compact_leaders(entry.get("leads", {}), metric_names)]
    where = f"On `{group}` ({len(g['frames'])} frames)"
    return f"{where}, best: " + " ".join(parts) if parts else f"{where} no denoiser was scored."


def headline(result: dict) -> str:
    groups = result.get("groups", {})
    if not groups:
        return "**Headline:** no frames were evaluated."
    names = result["metrics"]
    main, *hard = groups
    g = groups[main]
    parts = [f"**Headline** (`{main}`, {len(g['frames'])} frames; best mean per metric among the denoisers, "
             "significant when the paired bootstrap 95 % interval of the per-frame difference to the runner-up "
             "excludes 0)."]
    parts += [spp_sentence(spp, entry, names) for spp, entry in g["spp"].items()]
    if hard:
        parts.append("Hard cases, reported apart below and never averaged in (* = significant lead):")
        parts += [hard_clause(h, groups[h], names) for h in hard]
    return " ".join(parts)
