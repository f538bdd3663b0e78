"""No import circle between the evaluation and the model cards, lazy or under TYPE_CHECKING."""

from __future__ import annotations

import ast
from pathlib import Path

import sonarset.models.echopt.cards as cards
import sonarset.models.eval.evaluate as evaluate


def imported_modules(module) -> set[str]:
    """Every module a file imports anywhere: at the top, inside functions, under TYPE_CHECKING."""
    tree = ast.parse(Path(module.__file__).read_text())
    found = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.ImportFrom) and node.module:
            found.add(node.module)
            found.update(f"{node.module}.{a.name}" for a in node.names)
        elif isinstance(node, ast.Import):
            found.update(a.name for a in node.names)
    return found


def test_evaluate_and_cards_do_not_import_each_other_both_ways():
    evaluate_imports, cards_imports = imported_modules(evaluate), imported_modules(cards)
    assert not (cards.__name__ in evaluate_imports and evaluate.__name__ in cards_imports)
    assert cards.__name__ not in evaluate_imports  # the evaluation reads card_images, the shared piece
