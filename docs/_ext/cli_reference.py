"""A Sphinx directive that writes the command-line reference from the argparse parsers themselves, so the pages
cannot drift from the code: ``.. torchskin-cli::`` walks ``torchskin.cli.build_parser()`` and emits, for every
command and subcommand, a section with its description, its usage line and every option with its help and
default."""

from __future__ import annotations

import argparse
import importlib

from docutils import nodes
from docutils.parsers.rst import directives
from sphinx.application import Sphinx
from sphinx.util.docutils import SphinxDirective


def _subparsers(parser: argparse.ArgumentParser) -> argparse._SubParsersAction | None:
    return next((a for a in parser._actions if isinstance(a, argparse._SubParsersAction)), None)


def _option_text(action: argparse.Action) -> str:
    """``--name METAVAR`` / ``-h, --help`` / ``POSITIONAL`` as argparse's help shows it."""
    if not action.option_strings:
        return action.metavar if isinstance(action.metavar, str) else action.dest
    if action.nargs == 0:
        return ", ".join(action.option_strings)
    metavar = action.metavar if isinstance(action.metavar, str) else action.dest.upper()
    if action.choices is not None and action.metavar is None:
        metavar = "{" + ",".join(map(str, action.choices)) + "}"
    return ", ".join(f"{o} {metavar}" for o in action.option_strings)


def _help_text(action: argparse.Action, parser: argparse.ArgumentParser) -> str:
    text = action.help or ""
    if "%(" in text:  # argparse's own expansion (%(default)s, %(prog)s)
        text = text % {**vars(action), "prog": parser.prog}
    extra = []
    if action.required and action.option_strings:
        extra.append("required")
    if action.choices is not None and not isinstance(action, argparse._SubParsersAction):
        extra.append("one of: " + ", ".join(map(str, action.choices)))
    if (action.option_strings and action.nargs != 0 and action.default not in (None, argparse.SUPPRESS)
            and action.default != [] and "default" not in text):
        extra.append(f"default: {action.default}")
    return text + (f" ({'; '.join(extra)})" if extra else "")


class CliReference(SphinxDirective):
    """``.. torchskin-cli::`` with an optional ``:factory: module:function`` (default torchskin.cli:build_parser)."""

    has_content = False
    option_spec = {"factory": directives.unchanged}

    def run(self) -> list[nodes.Node]:
        module, _, func = self.options.get("factory", "torchskin.cli:build_parser").partition(":")
        parser = getattr(importlib.import_module(module), func)()
        return self._parser_nodes(parser, "torchskin", None)

    def _parser_nodes(self, parser: argparse.ArgumentParser, name: str, summary: str | None) -> list[nodes.Node]:
        section = nodes.section(ids=[nodes.make_id("cli " + name)], names=[nodes.fully_normalize_name(name)])
        section += nodes.title(text=name)
        self.state.document.note_implicit_target(section)
        if summary:
            section += nodes.paragraph(text=summary[0].upper() + summary[1:] + ".")
        if parser.description:
            section += nodes.paragraph(text=parser.description)
        formatter = argparse.HelpFormatter(parser.prog, width=88)  # the terminal's width would change the page
        formatter.add_usage(parser.usage, parser._actions, parser._mutually_exclusive_groups)
        usage = formatter.format_help().strip()
        section += nodes.literal_block(usage, usage, language="text")
        options = nodes.definition_list()
        sub = _subparsers(parser)
        for action in parser._actions:
            if isinstance(action, argparse._SubParsersAction) or action.help == argparse.SUPPRESS:
                continue
            item = nodes.definition_list_item()
            term = nodes.term()
            term += nodes.literal(text=_option_text(action))
            item += term
            item += nodes.definition("", nodes.paragraph(text=_help_text(action, parser)))
            options += item
        if options.children:
            section += nodes.rubric(text="Options")
            section += options
        if sub is not None:
            helps = {a.dest: a.help for a in sub._choices_actions}
            for child_name, child in sub.choices.items():
                section += self._parser_nodes(child, f"{name} {child_name}", helps.get(child_name))
        return [section]


def setup(app: Sphinx) -> dict:
    app.add_directive("torchskin-cli", CliReference)
    return {"version": "1", "parallel_read_safe": True, "parallel_write_safe": True}
