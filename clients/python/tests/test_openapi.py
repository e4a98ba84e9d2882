"""The client's models against the server's OpenAPI document, so they cannot drift.

The document is the running coordinator's ``/api/v1/openapi.json`` when
``TESSERA_SERVER`` names one (the end-to-end test sets it), else the copy the coordinator
serves, ``crates/tessera-coordinator/src/openapi.json``. Run with
``python3 -m unittest discover -s clients/python/tests``.
"""

import dataclasses
import json
import os
import re
import sys
import unittest

HERE = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, os.path.dirname(HERE))

from tessera_client import Client, models  # noqa: E402

REPO = os.path.abspath(os.path.join(HERE, "..", "..", ".."))
SERVED = os.path.join(REPO, "crates", "tessera-coordinator", "src", "openapi.json")

#: Python annotation base types against JSON schema types.
TYPES = {
    "int": "integer",
    "float": "number",
    "str": "string",
    "bool": "boolean",
    "FrameRange": "object",
    "Dict[str, Any]": "object",
    "List[float]": "array",
}


def load_document():
    if os.environ.get("TESSERA_SERVER"):
        return Client().openapi(), os.environ["TESSERA_SERVER"] + "/api/v1/openapi.json"
    with open(SERVED) as f:
        return json.load(f), SERVED


def parse_annotation(a: str):
    """(base type, nullable) of an annotation string such as ``Optional[int]``."""
    m = re.fullmatch(r"Optional\[(.*)\]", a)
    return (m.group(1), True) if m else (a, False)


class ModelsMatchTheOpenApiDocument(unittest.TestCase):
    @classmethod
    def setUpClass(cls):
        cls.doc, cls.source = load_document()
        cls.schemas = cls.doc["components"]["schemas"]

    def resolve(self, s):
        while "$ref" in s:
            s = self.schemas[s["$ref"].rsplit("/", 1)[1]]
        return s

    def check_model(self, cls, exact_required):
        schema = self.schemas[cls.SCHEMA]
        props = schema["properties"]
        fields = {f.name: f for f in dataclasses.fields(cls)}
        self.assertEqual(
            sorted(fields),
            sorted(props),
            f"{cls.__name__} against {cls.SCHEMA} in {self.source}",
        )
        required = set(schema.get("required", []))
        for name, f in fields.items():
            p = self.resolve(props[name])
            base, nullable = parse_annotation(f.type)
            where = f"{cls.__name__}.{name}"
            if "$ref" not in props[name] and base in TYPES:
                self.assertEqual(TYPES[base], p.get("type"), where)
            elif base == "JobSettings":
                self.assertEqual(props[name]["$ref"], "#/components/schemas/JobSettings", where)
            if p.get("nullable"):
                self.assertTrue(nullable, f"{where}: the schema's null needs Optional")
            elif nullable:
                # Optional without null in the schema only for a field an answer may lack.
                self.assertNotIn(name, required, f"{where}: never null, yet Optional")
                self.assertFalse(exact_required, f"{where}: never null, yet Optional")
            has_default = f.default is not dataclasses.MISSING or f.default_factory is not dataclasses.MISSING
            if exact_required or name in required:
                self.assertEqual(name in required, not has_default, f"{where}: required")
            if "enum" in f.metadata:
                self.assertEqual(sorted(f.metadata["enum"]), sorted(p["enum"]), f"{where}: enum")
            elif "enum" in p and name != "dry_run":
                self.fail(f"{where}: the schema has an enum {p['enum']} the model does not check")
            if f.default is not dataclasses.MISSING and f.default is not None and "default" in p:
                self.assertEqual(f.default, p["default"], f"{where}: default")

    def test_job_settings(self):
        # A request body: exactly the schema's fields (it refuses unknown ones), only
        # `scene` required, defaults the server's.
        self.check_model(models.JobSettings, exact_required=True)
        frames = self.schemas["JobSettings"]["properties"]["frames"]
        self.assertEqual(
            sorted(f.name for f in dataclasses.fields(models.FrameRange)),
            sorted(frames["properties"]),
        )
        self.assertEqual(sorted(frames["required"]), ["end", "start"])

    def test_job_status(self):
        self.check_model(models.JobStatus, exact_required=False)
        self.assertEqual(
            sorted(models.FINAL_STATES + ("queued", "running")),
            sorted(self.schemas["JobStatus"]["properties"]["state"]["enum"]),
        )

    def test_scene_uploaded_and_quote_interval(self):
        self.check_model(models.SceneUploaded, exact_required=True)
        self.check_model(models.QuoteInterval, exact_required=True)

    def test_error_codes(self):
        err = self.schemas["Error"]["properties"]["error"]
        self.assertEqual(sorted(models.ERROR_CODES), sorted(err["properties"]["code"]["enum"]))
        self.assertEqual(sorted(err["properties"]), ["code", "field", "message"])

    def test_every_quote_field_read_is_in_the_schema(self):
        for path in models.QUOTE_PATHS:
            s = self.schemas["Quote"]
            for key in path:
                s = self.resolve(s)
                if s.get("type") == "array":
                    s = self.resolve(s["items"])
                self.assertIn(key, s.get("properties", {}), f"Quote: {'.'.join(path)}")
                s = s["properties"][key]

    def test_every_path_the_client_calls_is_in_the_document(self):
        paths = self.doc["paths"]
        for path, method in [
            ("/scenes", "post"),
            ("/jobs", "post"),
            ("/jobs", "get"),
            ("/jobs/{id}", "get"),
            ("/jobs/{id}", "delete"),
            ("/jobs/{id}/image", "get"),
            ("/openapi.json", "get"),
        ]:
            self.assertIn(method, paths.get(path, {}), f"{method.upper()} {path}")
        params = {p["name"] for p in paths["/jobs/{id}/image"]["get"]["parameters"]}
        self.assertTrue({"format", "frame"} <= params)
        params = {p["name"] for p in paths["/jobs"]["post"]["parameters"]}
        self.assertTrue({"dry_run", "workers", "idempotency-key"} <= params)


if __name__ == "__main__":
    unittest.main()
