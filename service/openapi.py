"""``openapi.yaml``, the REST contract: the app's generated OpenAPI document, written as YAML.

``python -m service.openapi`` rewrites it after an API change; a test checks that the file and the
app agree.
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

OPENAPI_YAML = Path(__file__).resolve().parents[1] / "openapi.yaml"


def spec() -> dict:
    """The app's OpenAPI document as plain JSON data (settings do not change it)."""
    from service.app import create_app

    return json.loads(json.dumps(create_app().openapi()))


def dump(doc: dict) -> str:
    """YAML in the document's key order; text with line breaks as literal blocks."""
    import yaml

    class Dumper(yaml.SafeDumper):
        pass

    def text(dumper, value: str):
        style = "|" if "\n" in value and value == value.rstrip(" ") and "\n " not in value else None
        return dumper.represent_scalar("tag:yaml.org,2002:str", value, style=style)

    Dumper.add_representer(str, text)
    return yaml.dump(doc, Dumper=Dumper, sort_keys=False, allow_unicode=True, width=110)


def main(argv: list[str] | None = None) -> int:
    out = Path(argv[0]) if argv else OPENAPI_YAML
    out.write_text("# Generated from the app by `python -m service.openapi`; do not edit by hand.\n" + dump(spec()),
                   encoding="utf-8")
    print(f"wrote {out}")
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
