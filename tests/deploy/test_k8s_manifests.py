"""The Kubernetes manifests agree with the image, the service and the client they run (CI validates their schema
and scans them: scripts/check_manifests.sh). Each check here fails when one side is renamed or changed alone."""

from __future__ import annotations

import re
from pathlib import Path

import pytest
import yaml

from pranet.client.batch import BatchSummary
from pranet.client.cli import build_parser
from pranet.service.settings import Settings

REPO = Path(__file__).resolve().parents[2]
K8S = REPO / "deploy" / "k8s"
THREAD_VARIABLES = {"PRANET_THREADS", "OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"}


def load(name: str) -> list[dict]:
    return [doc for doc in yaml.safe_load_all((K8S / name).read_text()) if doc]


def one(name: str) -> dict:
    (doc,) = load(name)
    return doc


def container(workload: dict) -> dict:
    (c,) = workload["spec"]["template"]["spec"]["containers"]
    return c


def env_of(c: dict) -> dict[str, dict]:
    return {e["name"]: e for e in c["env"]}


WORKLOADS = ["deployment.yaml", "batch/register-many-job.yaml"]


def test_every_manifest_is_in_the_namespace() -> None:
    namespace = one("namespace.yaml")["metadata"]["name"]
    for path in K8S.rglob("*.yaml"):
        for doc in yaml.safe_load_all(path.read_text()):
            if doc and doc["kind"] != "Namespace":
                assert doc["metadata"]["namespace"] == namespace, path


def test_threads_are_the_cpu_request() -> None:
    """onnxruntime, OpenMP and BLAS get as many threads as the pod requested cores, read from the request itself,
    and the pod computes one registration at a time: no oversubscription."""
    c = container(one("deployment.yaml"))
    env = env_of(c)
    for name in THREAD_VARIABLES:
        ref = env[name]["valueFrom"]["resourceFieldRef"]
        assert ref == {"containerName": c["name"], "resource": "requests.cpu", "divisor": "1"}, name
    assert env["PRANET_MAX_CONCURRENCY"]["value"] == "1"
    assert env["PRANET_WORKERS"]["value"] == "1"  # one uvicorn process per pod


def test_the_pods_run_as_the_images_user_read_only_and_unprivileged() -> None:
    user = re.search(r"^USER (\d+):(\d+)$", (REPO / "Dockerfile").read_text(), re.M)
    assert user, "the Dockerfile names its user by number"
    uid, gid = int(user.group(1)), int(user.group(2))
    for name in WORKLOADS:
        pod = one(name)["spec"]["template"]["spec"]
        assert pod["securityContext"]["runAsNonRoot"] is True
        assert (pod["securityContext"]["runAsUser"], pod["securityContext"]["runAsGroup"]) == (uid, gid)
        assert pod["securityContext"]["seccompProfile"] == {"type": "RuntimeDefault"}
        assert pod["automountServiceAccountToken"] is False
        sc = container(one(name))["securityContext"]
        assert sc["readOnlyRootFilesystem"] is True and sc["allowPrivilegeEscalation"] is False
        assert sc["capabilities"] == {"drop": ["ALL"]} and sc["runAsUser"] == uid


def test_probes_use_the_services_routes_and_its_probe() -> None:
    c = container(one("deployment.yaml"))
    assert c["startupProbe"]["httpGet"]["path"] == "/health"
    assert c["livenessProbe"]["httpGet"]["path"] == "/health"
    assert c["readinessProbe"]["exec"]["command"] == ["python", "-m", "pranet.service.probe", "ready"]
    port = next(p for p in c["ports"] if p["name"] == c["livenessProbe"]["httpGet"]["port"])
    assert c["args"] == ["--host", "0.0.0.0", "--port", str(port["containerPort"])]


def test_the_grace_period_covers_the_drain() -> None:
    pod = one("deployment.yaml")["spec"]["template"]["spec"]
    (c,) = pod["containers"]
    command = c["lifecycle"]["preStop"]["exec"]["command"]
    assert command[0] == "sleep"
    assert pod["terminationGracePeriodSeconds"] > float(command[1]) + Settings().shutdown_timeout_s


def test_service_hpa_pdb_and_policy_select_the_deployments_pods() -> None:
    deployment = one("deployment.yaml")
    labels = deployment["spec"]["template"]["metadata"]["labels"]
    assert deployment["spec"]["selector"]["matchLabels"].items() <= labels.items()
    service = one("service.yaml")
    assert service["spec"]["selector"].items() <= labels.items()
    assert service["spec"]["ports"][0]["targetPort"] in {p["name"] for p in container(deployment)["ports"]}
    assert one("pdb.yaml")["spec"]["selector"]["matchLabels"].items() <= labels.items()
    target = one("hpa.yaml")["spec"]["scaleTargetRef"]
    assert (target["kind"], target["name"]) == ("Deployment", deployment["metadata"]["name"])
    policies = {p["metadata"]["name"]: p for p in load("networkpolicy.yaml")}
    assert policies["pranet-server"]["spec"]["podSelector"]["matchLabels"].items() <= labels.items()


def test_the_api_key_comes_from_the_example_secrets_name_and_key() -> None:
    secret = one("examples/secret.yaml")
    for name in WORKLOADS:
        ref = env_of(container(one(name)))["PRANET_API_KEY"]["valueFrom"]["secretKeyRef"]
        assert ref["name"] == secret["metadata"]["name"] and ref["key"] in secret["stringData"]


# --- the batch Job ---------------------------------------------------------------------------------------------


def job_command(index: int) -> list[str]:
    """The Job's command as the kubelet runs it in pod ``index``: $(JOB_COMPLETION_INDEX) expanded."""
    c = container(one("batch/register-many-job.yaml"))
    assert "JOB_COMPLETION_INDEX" in env_of(c), "$(JOB_COMPLETION_INDEX) expands only from a declared variable"
    return [arg.replace("$(JOB_COMPLETION_INDEX)", str(index)) for arg in c["command"]]


def test_job_shards_are_its_completions() -> None:
    spec = one("batch/register-many-job.yaml")["spec"]
    assert spec["completionMode"] == "Indexed"
    for index in (0, spec["completions"] - 1):
        command = job_command(index)
        assert command[:2] == ["pranet-client", "register-many"]
        args = build_parser().parse_args(command[1:])
        assert (args.shard_index, args.shard_count) == (index, spec["completions"])
        assert str(index) in args.out.name  # each shard its own results file, resumed by a retried pod


def test_job_talks_to_the_service_and_fails_an_index_only_on_what_a_retry_cannot_fix() -> None:
    job = one("batch/register-many-job.yaml")
    service = one("service.yaml")
    url = env_of(container(job))["PRANET_URL"]["value"]
    assert url == f"http://{service['metadata']['name']}.{service['metadata']['namespace']}.svc"
    (fail_index,) = [r for r in job["spec"]["podFailurePolicy"]["rules"] if r["action"] == "FailIndex"]
    # register-many exits 1 when it cannot start, 2 on bad arguments; its summary says the rest.
    failed_for_good = BatchSummary(Path("out.jsonl"), total=1, failed=1).exit_code
    service_unavailable = BatchSummary(Path("out.jsonl"), total=1, not_done=1).exit_code
    assert set(fail_index["onExitCodes"]["values"]) == {1, 2, failed_for_good}
    assert service_unavailable not in fail_index["onExitCodes"]["values"]  # retried: the pod resumes the shard


@pytest.mark.parametrize("name", WORKLOADS)
def test_the_image_is_the_same_everywhere(name: str) -> None:
    assert container(one(name))["image"] == container(one("deployment.yaml"))["image"]
