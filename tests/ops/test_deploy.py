"""deploy/: the Kubernetes manifests agree with each other, the Dockerfile and the service."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import yaml

ROOT = Path(__file__).resolve().parents[2]


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


def test_readiness_on_readyz_liveness_on_healthz():
    """Separate endpoints (issue 30): a draining pod's /readyz answers 503 while its /healthz stays 200."""
    for probe, path in (("readinessProbe", "/readyz"), ("livenessProbe", "/healthz")):
        get = CONTAINER[probe]["httpGet"]
        assert get["path"] == path and get["port"] in ("http", int(ENV["JOINTLIMITS_PORT"]))


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
    """SIGTERM comes at once (no preStop: the drain is the server's, JOINTLIMITS_SHUTDOWN_DELAY), then the
    graceful timeout; both fit before SIGKILL."""
    from jointlimits.service.settings import TABLE

    assert "preStop" not in CONTAINER.get("lifecycle", {})  # it would add to the delay, /readyz still 200
    delay = float(ENV.get("JOINTLIMITS_SHUTDOWN_DELAY") or next(s.default for s in TABLE if s.name == "shutdown_delay"))
    assert delay > 0
    assert delay + float(ENV["JOINTLIMITS_GRACEFUL_TIMEOUT"]) < POD["terminationGracePeriodSeconds"]


def test_runs_as_the_images_non_root_user():
    user = next(line.split()[1] for line in (ROOT / "Dockerfile").read_text().splitlines() if line.startswith("USER "))
    assert POD["securityContext"]["runAsNonRoot"] is True
    assert str(POD["securityContext"]["runAsUser"]) == user.split(":")[0]
    assert CONTAINER["securityContext"]["readOnlyRootFilesystem"] is True
    # ... so /tmp (tempfile's directory, where the Prometheus multiprocess files go) must be writable.
    assert any(m["mountPath"] == "/tmp" for m in CONTAINER["volumeMounts"])


def _quantity(q: str) -> int:
    """A Kubernetes memory quantity in bytes (`2Gi`, `512Mi`, `1G`, plain bytes)."""
    units = {"Ki": 2**10, "Mi": 2**20, "Gi": 2**30, "Ti": 2**40, "K": 10**3, "M": 10**6, "G": 10**9, "T": 10**12}
    for suffix, factor in units.items():
        if q.endswith(suffix) and q[: -len(suffix)].isdigit():
            return int(q[: -len(suffix)]) * factor
    return int(q)


def test_memory_limit_follows_from_the_request_limits(monkeypatch):
    """The pod's memory limit holds every worker at the peak its limits admit (jointlimits.service.sizing), and not far more."""
    from jointlimits.service import sizing
    from jointlimits.service.settings import Settings

    for name in [n for n in os.environ if n.startswith("JOINTLIMITS_")]:
        monkeypatch.delenv(name)
    for name, value in ENV.items():
        if value is not None:
            monkeypatch.setenv(name, value)
    settings = Settings()  # the container's settings: the manifest's env over the defaults
    workers = int(ENV["JOINTLIMITS_WORKERS"])
    tmpfs = sum(_quantity(v["emptyDir"]["sizeLimit"]) for v in POD["volumes"] if v.get("emptyDir", {}).get("medium") == "Memory")
    need = sizing.pod_bytes(settings, workers) + tmpfs  # an in-memory emptyDir counts against the limit
    limit = _quantity(CONTAINER["resources"]["limits"]["memory"])
    assert need <= limit, f"{workers} workers at these limits may need {need / 2**20:.0f} MiB > the {limit / 2**20:.0f} MiB limit"
    assert limit <= 1.5 * need, "the limit wastes memory the limits can never use; lower it or raise the limits"
    assert _quantity(CONTAINER["resources"]["requests"]["memory"]) <= limit


def test_the_readmes_sizing_figures_are_the_rules(monkeypatch):
    """docs/deployment.md (moved from the README), "Sizing a pod": the figures per worker and per 2-worker pod at the defaults, and per worker in the manifest."""
    from jointlimits.service import sizing
    from jointlimits.service.settings import Settings

    for name in [n for n in os.environ if n.startswith("JOINTLIMITS_")]:
        monkeypatch.delenv(name)
    readme = (ROOT / "docs" / "deployment.md").read_text()
    defaults = Settings()
    assert f"a worker may reach {sizing.worker_bytes(defaults) / 2**30:.1f} GiB" in readme
    assert f"2 workers need a {sizing.pod_bytes(defaults, 2) / 2**30:.1f} GiB pod" in readme
    for name, value in ENV.items():
        if value is not None:
            monkeypatch.setenv(name, value)
    assert f"{sizing.worker_bytes(Settings()) / 2**20:.0f} MiB per worker" in readme


PDB = load("pdb.yaml")


def test_the_hpa_owns_the_replica_count():
    """A `replicas` in the Deployment would reset the autoscaler's count on every `kubectl apply`."""
    assert "replicas" not in DEPLOYMENT["spec"]
    assert HPA["spec"]["minReplicas"] >= 2  # so that the disruption budget below can evict one


def test_a_disruption_budget_keeps_a_pod_up():
    assert PDB["kind"] == "PodDisruptionBudget"
    labels = DEPLOYMENT["spec"]["template"]["metadata"]["labels"]
    assert PDB["spec"]["selector"]["matchLabels"].items() <= labels.items()
    assert PDB["spec"]["maxUnavailable"] < HPA["spec"]["minReplicas"]


def test_memory_is_requested_as_limited():
    """The sizing rule is what a pod may reach at any time: the scheduler reserves all of it."""
    resources = CONTAINER["resources"]
    assert _quantity(resources["requests"]["memory"]) == _quantity(resources["limits"]["memory"])


def _kubernetes_validate(*paths: Path) -> subprocess.CompletedProcess:
    exe = Path(sys.executable).with_name("kubernetes-validate")
    return subprocess.run([str(exe), "--strict", *map(str, paths)], capture_output=True, text=True, timeout=120)


def test_kubernetes_validate_strict_passes_on_deploy():
    manifests = sorted((ROOT / "deploy").glob("*.yaml"))
    assert len(manifests) == 4
    done = _kubernetes_validate(*manifests)
    assert done.returncode == 0, done.stdout + done.stderr
    assert done.stdout.count("passed") == len(manifests), done.stdout


def test_kubernetes_validate_strict_rejects_an_unknown_field(tmp_path):
    """The check above can fail: a misspelt field is refused under --strict."""
    bad = tmp_path / "bad.yaml"
    bad.write_text((ROOT / "deploy" / "pdb.yaml").read_text().replace("maxUnavailable", "maxUnavailabel"))
    assert _kubernetes_validate(bad).returncode != 0
