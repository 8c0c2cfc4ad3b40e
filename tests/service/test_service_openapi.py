"""openapi.yaml is the REST contract: it must equal the app's generated spec, and document errors."""

from __future__ import annotations

import yaml

from service.openapi import OPENAPI_YAML, spec


def test_openapi_yaml_equals_the_generated_spec():
    on_disk = yaml.safe_load(OPENAPI_YAML.read_text(encoding="utf-8"))
    assert on_disk == spec(), "openapi.yaml is stale: run `python -m service.openapi`"


def test_every_error_answer_is_documented_as_json_with_a_detail():
    doc = spec()
    assert doc["components"]["schemas"]["ErrorBody"]["required"] == ["detail"]
    for path, ops in doc["paths"].items():
        for method, op in ops.items():
            codes = {int(c) for c in op["responses"]}
            if path.startswith("/v1/"):
                assert {401, 422, 500} <= codes, (method, path, codes)
            for code, resp in op["responses"].items():
                if int(code) < 400:
                    continue
                schema = resp["content"]["application/json"]["schema"]["$ref"]
                assert schema.endswith(("/ErrorBody", "/Health")), (method, path, code, schema)


def test_the_api_names_the_clients_depend_on():
    doc = spec()
    paths = doc["paths"]
    assert {"post", "get"} <= set(paths["/v1/jobs"])
    assert {"get", "delete"} <= set(paths["/v1/jobs/{job_id}"])
    form = doc["components"]["schemas"]["Body_submit_job_v1_jobs_post"]
    assert "keypoints" in form["required"] and {"calibration", "calibration_id", "options"} <= set(form["properties"])
    fmt = next(p for p in paths["/v1/jobs/{job_id}/result"]["get"]["parameters"] if p["name"] == "format")
    assert {"csv", "h5", "json"} <= set(fmt["schema"]["enum"])
    status = doc["components"]["schemas"]["JobOut"]["properties"]["status"]
    assert status["enum"] == ["queued", "running", "succeeded", "failed", "cancelled"]
    assert {"stage", "iteration", "cost", "fraction"} <= set(doc["components"]["schemas"]["Progress"]["properties"])
    cal_form = doc["components"]["schemas"]["Body_submit_calibration_v1_calibrations_post"]
    assert "board" in cal_form["required"]
    assert {"detections", "videos", "intrinsics", "options"} <= set(cal_form["properties"])
    assert {"get", "delete"} <= set(paths["/v1/calibrations/{calibration_id}"])
    files = next(p for p in paths["/v1/calibrations/{calibration_id}/{file}"]["get"]["parameters"]
                 if p["name"] == "file")
    assert {"calibration.toml", "scene.json", "report.json", "rig.png"} <= set(files["schema"]["enum"])
    for p in ("/v1/skeletons", "/healthz", "/metrics"):
        assert "get" in paths[p]


def test_the_spec_declares_the_bearer_scheme_and_the_refusals_of_a_submission():
    """Issue item 11: the spec had no security scheme and no 400 for a body that is not multipart."""
    doc = spec()
    bearer = doc["components"]["securitySchemes"]["bearer"]
    assert bearer == {"type": "http", "scheme": "bearer", "description": bearer["description"]}
    for path, ops in doc["paths"].items():
        for method, op in ops.items():
            assert (op.get("security") == [{"bearer": []}]) == path.startswith("/v1/"), (method, path)
    submit = doc["paths"]["/v1/jobs"]["post"]["responses"]
    assert {"400", "413", "422", "429", "507"} <= set(submit)
