"""Messages for the user collected while exporting / baking / rendering (no bpy)."""

from __future__ import annotations


class ExportError(ValueError):
    """Nothing exportable (or an unusable object); the message is meant for the user."""


class Report:
    """Ordered, de-duplicated (level, message) pairs; level is 'INFO', 'WARNING' or 'ERROR'
    (Blender's report types)."""

    def __init__(self):
        self.items: list[tuple[str, str]] = []

    def add(self, level: str, msg: str) -> None:
        if (level, msg) not in self.items:
            self.items.append((level, msg))

    def info(self, msg: str) -> None:
        self.add("INFO", msg)

    def warning(self, msg: str) -> None:
        self.add("WARNING", msg)

    def error(self, msg: str) -> None:
        self.add("ERROR", msg)

    def messages(self, level: str | None = None) -> list[str]:
        return [m for lv, m in self.items if level is None or lv == level]

    def emit(self, report_fn, min_level: str = "INFO") -> None:
        """Send every item to an operator's / engine's ``self.report``."""
        order = {"INFO": 0, "WARNING": 1, "ERROR": 2}
        for lv, m in self.items:
            if order[lv] >= order[min_level]:
                report_fn({lv}, m)

    def __bool__(self) -> bool:
        return bool(self.items)

    def __str__(self) -> str:
        return "\n".join(f"{lv}: {m}" for lv, m in self.items)
