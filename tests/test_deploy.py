"""deploy/: the Kubernetes manifests agree with each other, the Dockerfile and the service."""

from __future__ import annotations

from pathlib import Path

import yaml

ROOT = Path(__file__).resolve().parent.parent


def load(name: str) -> dict:
    docs = [d for d in yaml.safe_load_all((ROOT / "deploy" / name).read_text()) if d]
    assert len(docs) == 1
    return docs[0]


DEPLOYMENT, SERVICE, HPA = load("deployment.yaml"), load("service.yaml"), load("hpa.yaml")
POD = DEPLOYMENT["spec"]["template"]["spec"]
CONTAINER = POD["containers"][0]
ENV = {e["name"]: e.get("value") for e in CONTAINER["env"]}


def test_kinds():
    assert (DEPLOYMENT["kind"], SERVICE["kind"], HPA["kind"]) == ("Deployment", "Service", "HorizontalPodAutoscaler")


def test_probes_on_healthz():
    for probe in ("readinessProbe", "livenessProbe"):
        get = CONTAINER[probe]["httpGet"]
        assert get["path"] == "/healthz" and get["port"] in ("http", int(ENV["JOINTLIMITS_PORT"]))


def test_ports_line_up():
    port = int(ENV["JOINTLIMITS_PORT"])
    assert {p["name"]: p["containerPort"] for p in CONTAINER["ports"]}["http"] == port
    assert SERVICE["spec"]["ports"][0]["targetPort"] in ("http", port)
    labels = DEPLOYMENT["spec"]["template"]["metadata"]["labels"]
    assert DEPLOYMENT["spec"]["selector"]["matchLabels"].items() <= labels.items()
    assert SERVICE["spec"]["selector"].items() <= labels.items()


def test_hpa_scales_the_deployment_on_cpu():
    spec = HPA["spec"]
    assert spec["scaleTargetRef"]["kind"] == "Deployment" and spec["scaleTargetRef"]["name"] == DEPLOYMENT["metadata"]["name"]
    assert [m["resource"]["name"] for m in spec["metrics"]] == ["cpu"]
    assert 1 <= spec["minReplicas"] <= spec["maxReplicas"]
    assert "cpu" in CONTAINER["resources"]["requests"]  # utilisation is measured against the request


def test_workers_match_the_cpu_request():
    assert int(ENV["JOINTLIMITS_WORKERS"]) == int(CONTAINER["resources"]["requests"]["cpu"])


def test_graceful_shutdown_fits_the_grace_period():
    pre_stop = CONTAINER["lifecycle"]["preStop"]["exec"]["command"]
    assert pre_stop[0] == "sleep"
    assert int(pre_stop[1]) + float(ENV["JOINTLIMITS_GRACEFUL_TIMEOUT"]) < POD["terminationGracePeriodSeconds"]


def test_runs_as_the_images_non_root_user():
    user = next(line.split()[1] for line in (ROOT / "Dockerfile").read_text().splitlines() if line.startswith("USER "))
    assert POD["securityContext"]["runAsNonRoot"] is True
    assert str(POD["securityContext"]["runAsUser"]) == user.split(":")[0]
    assert CONTAINER["securityContext"]["readOnlyRootFilesystem"] is True
    # ... so /tmp (tempfile's directory, where the Prometheus multiprocess files go) must be writable.
    assert any(m["mountPath"] == "/tmp" for m in CONTAINER["volumeMounts"])
