"""``--help`` of every subcommand: its page opens with the line the top-level list shows, every option says what
it does, and no help text carries reStructuredText markup (argparse prints it literally)."""
import argparse

import pytest

from mcdenoise.pipeline.cli import build_parser, main

PARSER = build_parser()
SUB = next(a for a in PARSER._actions if isinstance(a, argparse._SubParsersAction))
SUMMARY = {c.dest: c.help for c in SUB._choices_actions}


def test_the_top_level_page_lists_every_subcommand_without_markup(capsys):
    with pytest.raises(SystemExit) as exit_:
        main(["--help"])
    out = capsys.readouterr().out
    assert exit_.value.code == 0 and "``" not in out
    assert all(name in out for name in SUB.choices)


@pytest.mark.parametrize("name", sorted(SUB.choices))
def test_every_subcommand_page_opens_with_its_summary_and_documents_every_option(name, capsys):
    with pytest.raises(SystemExit) as exit_:
        main([name, "--help"])
    out = capsys.readouterr().out
    assert exit_.value.code == 0
    page = SUB.choices[name]
    summary = SUMMARY[name]
    assert page.description and page.description.lower().startswith(summary.lower()[:40])
    undocumented = [a.option_strings or [a.dest] for a in page._actions
                    if not isinstance(a, argparse._HelpAction) and not a.help]
    assert undocumented == []
    texts = [page.description, summary] + [a.help for a in page._actions]
    assert not any("``" in t for t in texts if t)
    assert " ".join(page.description.split()[:4]) in " ".join(out.split())


def test_denoise_says_where_its_weights_come_from():
    text = " ".join(SUB.choices["denoise"].description.split())
    assert "diffusion_spp" in text and "train/shipped" in text
