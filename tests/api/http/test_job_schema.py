"""``/openapi.json`` shows what each kind of job returns: the job is a union discriminated by
its ``kind``, each member's ``result`` the kind's typed model (an approach's and a track's by
their ``mode``), so a PLC programmer reading ``/docs`` sees every field of a finished job."""

from __future__ import annotations

from pathlib import Path
from typing import Any

from fastapi.testclient import TestClient

from api.app import create_app
from tests.support.cell import running_cell, sim_config


def _resolve(schema: dict[str, Any], components: dict[str, Any]) -> dict[str, Any]:
    while "$ref" in schema:
        schema = components[schema["$ref"].rsplit("/", 1)[-1]]
    return schema


def _members(schema: dict[str, Any], components: dict[str, Any]) -> dict[str, dict[str, Any]]:
    """A discriminated union's members by their discriminator's value (null dropped)."""
    union = next(s for s in schema.get("anyOf", [schema]) if "oneOf" in s)
    return {value: components[ref.rsplit("/", 1)[-1]]
            for value, ref in union["discriminator"]["mapping"].items()}


def test_the_job_schema_is_a_union_by_kind_with_each_kind_s_typed_result(
        tmp_path: Path) -> None:
    with running_cell(sim_config(tmp_path)) as cell, TestClient(create_app(cell)) as client:
        schema = client.get("/openapi.json").json()
    components = schema["components"]["schemas"]
    body = schema["paths"]["/api/v1/jobs/{job_id}"]["get"]["responses"]["200"]["content"]
    job = body["application/json"]["schema"]
    assert job["discriminator"]["propertyName"] == "kind"
    jobs = _members(job, components)
    assert set(jobs) == {"approach", "track", "home", "hand_eye_calibration", "pick",
                         "calibration_reference", "calibration_check"}
    for kind, member in jobs.items():
        assert member["properties"]["kind"]["const"] == kind
    pick = _resolve(jobs["pick"]["properties"]["result"]["anyOf"][0], components)
    assert {"part", "grip", "phases_s", "place", "cycle_s"} <= set(pick["required"])
    check = _resolve(jobs["calibration_check"]["properties"]["result"]["anyOf"][0], components)
    assert {"verdict", "tcp_error_mm", "tcp_error_deg", "views"} <= set(check["required"])

    approach = _members(jobs["approach"]["properties"]["result"], components)
    assert set(approach) == {"look_and_move", "servo", "ibvs"}
    for mode, result in approach.items():
        fields = set(result["properties"])
        assert {"mode", "converged", "estimated_error_mm", "estimated_error_basis",
                "consistency", "first_locate_s"} <= fields, mode
        assert result["properties"]["mode"]["const"] == mode
    assert {"reach_error_mm", "cycles", "closing", "pose_source"} \
        <= set(approach["look_and_move"]["properties"])
    assert {"reach_error_mm", "time_to_converge_s", "error_history", "pose_latency_ms"} \
        <= set(approach["servo"]["required"])
    assert {"image_error_px_rms", "phases_s", "settle_steps_mm_deg"} \
        <= set(approach["ibvs"]["properties"])
    basis = _resolve(approach["servo"]["properties"]["estimated_error_basis"], components)
    assert basis["properties"]["frame"]["enum"] == ["base", "camera", "image"]
    consistency = _resolve(approach["servo"]["properties"]["consistency"], components)
    assert {"verdict", "codes", "findings", "motion"} <= set(consistency["required"])

    track = _members(jobs["track"]["properties"]["result"], components)
    assert set(track) == {"track", "ibvs_track"}
    assert {"duration_s", "rms_error_mm", "target_velocity_mm_s"} \
        <= set(track["track"]["properties"])
    assert {"duration_s", "image_error_px_rms"} <= set(track["ibvs_track"]["properties"])

    home = _resolve(next(s for s in jobs["home"]["properties"]["result"]["anyOf"]
                         if "$ref" in s), components)
    assert set(home["required"]) == {"joints_deg", "T_base_tcp"}
    routine = _resolve(next(s for s in jobs["hand_eye_calibration"]["properties"]["result"]
                            ["anyOf"] if "$ref" in s), components)
    assert {"chosen", "T_flange_camera", "methods", "verdict", "failed_views",
            "change_from_current", "dataset"} <= set(routine["required"])

    located = schema["paths"]["/api/v1/locate"]["post"]["responses"]["200"]["content"]
    # the single target's answer, or with {"all": true} every part's
    single, every = (_resolve(s, components)
                     for s in located["application/json"]["schema"]["anyOf"])
    assert {"T_base_target", "quality", "consistency"} <= set(single["required"])
    assert {"instances", "unresolved", "order"} <= set(every["required"])
    instance = _resolve(every["properties"]["instances"]["items"], components)
    assert {"id", "T_base_target", "quality", "flags", "pickable"} <= set(instance["required"])
