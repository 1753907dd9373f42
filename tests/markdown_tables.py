"""Reading the Markdown tables that the benchmark scripts write, for the tests of those scripts."""


def tables(text: str) -> list[list[str]]:
    """The Markdown tables of ``text``, each as its lines (header, rule, rows)."""
    found, current = [], []
    for line in text.splitlines() + [""]:
        if line.startswith("|"):
            current.append(line)
        elif current:
            found.append(current)
            current = []
    return found


def columns(line: str) -> int:
    """Number of cells of one table line."""
    return line.count("|") - 1
