"""deploy/*.yaml against Kubernetes' own schema: offline, and with kubectl.

Offline (always runs): ``kubernetes-validate`` (a dev dependency) bundles the JSON
schemas generated from Kubernetes' OpenAPI for each release and validates every
object of every manifest strictly (unknown fields refused) against the oldest
release the manifests need (1.29: ``backoffLimitPerIndex``) and the newest it ships.
It reads only its package data (checked in a network namespace with no network).

With a cluster: ``kubectl apply --dry-run=client --validate=strict`` validates each
object against the OpenAPI schema it downloads from the cluster's API server (unknown fields, wrong
``kubectl apply --dry-run=client --validate=strict`` validates each object against the
OpenAPI schema it downloads from the cluster's API server (unknown fields, wrong
types, bad kinds); even a client dry run needs that server. Where kubectl or a
reachable cluster is missing (this CI machine: kubectl is installed, no cluster), the
test is skipped with kubectl's own reason. deploy/'s commands are checked against the
hil command line in tests/harness/search/test_search.py.
"""

from __future__ import annotations

import shutil
import subprocess
from pathlib import Path

import pytest
import yaml

ROOT = Path(__file__).resolve().parents[1]
MANIFESTS = sorted((ROOT / "deploy").glob("*.yaml"))
# What kubectl says when it has no API server to take the schema from.
_NO_SERVER = ("failed to download openapi", "connection refused", "unable to recognize",
              "couldn't get current server API group list", "no configuration has been provided")


def _kubectl(*args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run(["kubectl", *args], capture_output=True, text=True, timeout=60, cwd=ROOT,
                          stdin=subprocess.DEVNULL)


# The oldest Kubernetes the manifests need (backoffLimitPerIndex, Indexed Jobs) and the newest schema shipped.
K8S_VERSIONS = ("1.29.0", "1.37.0")
BAD_JOB = ("apiVersion: batch/v1\nkind: Job\nmetadata: {name: bad}\nspec:\n  completionz: 3\n"
           "  template: {spec: {restartPolicy: Never, containers: [{name: a, image: b}]}}\n")


def test_there_are_manifests_to_validate():
    assert {p.name for p in MANIFESTS} >= {"search-job.yaml", "merge-job.yaml", "dask-cluster.yaml"}


@pytest.mark.parametrize("version", K8S_VERSIONS)
@pytest.mark.parametrize("manifest", MANIFESTS, ids=lambda p: p.name)
def test_manifest_passes_the_bundled_kubernetes_schema_strictly(manifest, version):
    import kubernetes_validate

    docs = [d for d in yaml.safe_load_all(manifest.read_text()) if d is not None]
    assert docs
    for doc in docs:
        try:
            kubernetes_validate.validate(doc, version, strict=True)
        except kubernetes_validate.ValidationError as err:
            pytest.fail(f"{manifest.name}: {doc['kind']} {doc['metadata']['name']} at "
                        f"{'.'.join(map(str, err.path))}: {err.message} (Kubernetes {version})")
    assert {d["kind"] for d in docs} <= {"Job", "PersistentVolumeClaim", "Service", "Deployment"}


@pytest.mark.parametrize(("text", "path", "says"), [
    (BAD_JOB, [], "'completionz' was unexpected"),
    (BAD_JOB.replace("completionz: 3", "completions: four"), ["completions"], "'four' is not of type"),
    (BAD_JOB.replace("completionz: 3", "completionMode: Indexed").replace("name: a, image: b",
                                                                         "name: a, image: b, cmd: [x]"),
     ["template", "spec", "containers", 0], "'cmd' was unexpected"),
], ids=["unknown-field", "wrong-type", "nested-unknown-field"])
def test_the_offline_validator_refuses_a_bad_job(text, path, says):
    """The validator is real: misspelt and mistyped fields are refused, where they are."""
    import kubernetes_validate

    with pytest.raises(kubernetes_validate.ValidationError) as err:
        kubernetes_validate.validate(yaml.safe_load(text), K8S_VERSIONS[-1], strict=True)
    assert says in err.value.message and list(err.value.path) == ["spec", *path], (err.value.message,
                                                                                    list(err.value.path))


@pytest.mark.parametrize("manifest", MANIFESTS, ids=lambda p: p.name)
def test_manifest_passes_kubectl_strict_client_dry_run(manifest):
    if shutil.which("kubectl") is None:
        pytest.skip("kubectl is not installed")
    p = _kubectl("apply", "--dry-run=client", "--validate=strict", "-o", "name", "-f", str(manifest))
    if p.returncode != 0 and any(s in p.stderr for s in _NO_SERVER):
        first = next((ln for ln in p.stderr.splitlines() if ln.strip()), "")
        pytest.skip(f"kubectl's schema validation needs a reachable cluster (KUBECONFIG): {first[:200]}")
    assert p.returncode == 0, p.stderr
    kinds = {line.split("/")[0] for line in p.stdout.split()}
    assert kinds and all("." in k or k in {"job", "persistentvolumeclaim", "service"} for k in kinds), p.stdout


def test_kubectl_refuses_an_unknown_field_when_it_can_validate(tmp_path):
    """The validator is real: a misspelt Job field is refused (skipped without a cluster)."""
    if shutil.which("kubectl") is None:
        pytest.skip("kubectl is not installed")
    bad = tmp_path / "bad.yaml"
    bad.write_text("apiVersion: batch/v1\nkind: Job\nmetadata: {name: bad}\nspec:\n  completionz: 3\n"
                   "  template: {spec: {restartPolicy: Never, containers: [{name: a, image: b}]}}\n")
    p = _kubectl("apply", "--dry-run=client", "--validate=strict", "-f", str(bad))
    if p.returncode != 0 and any(s in p.stderr for s in _NO_SERVER):
        pytest.skip("kubectl's schema validation needs a reachable cluster (KUBECONFIG)")
    assert p.returncode != 0 and "completionz" in p.stderr, (p.stdout, p.stderr)


def test_the_dask_manifest_wires_client_workers_and_scheduler_together():
    """The client Job's command is a valid ``hil search --scheduler`` line naming the
    scheduler's Service and port, and the workers join that address as non-daemonic
    single-thread processes (an episode starts processes of its own)."""
    from hil.harness.search.cli import run_parser

    docs = {(d["kind"], d["metadata"]["name"]): d
            for d in yaml.safe_load_all((ROOT / "deploy" / "dask-cluster.yaml").read_text())}
    svc = docs[("Service", "hil-dask-scheduler")]
    (port,) = [p["port"] for p in svc["spec"]["ports"]]
    address = f"tcp://{svc['metadata']['name']}:{port}"
    sched = docs[("Deployment", "hil-dask-scheduler")]["spec"]["template"]
    assert svc["spec"]["type"] == "ClusterIP" and svc["spec"]["selector"].items() <= sched["metadata"]["labels"].items()
    (sc,) = sched["spec"]["containers"]
    assert sc["command"][:2] == ["dask", "scheduler"] and str(port) in sc["command"]

    (client,) = docs[("Job", "hil-search-dask")]["spec"]["template"]["spec"]["containers"]
    argv = client["command"] + client["args"]
    assert argv[:2] == ["hil", "search"]
    args = run_parser().parse_args(argv[2:])
    assert args.scheduler == address and args.resume and (ROOT / args.spec).is_file()

    (worker,) = docs[("Deployment", "hil-dask-worker")]["spec"]["template"]["spec"]["containers"]
    env = {e["name"]: e["value"] for e in worker["env"]}
    assert env["DASK_DISTRIBUTED__WORKER__DAEMON"] == "False"
    wargs = [a.replace("$(WORKER_PROCS)", env["WORKER_PROCS"]) for a in worker["args"]]
    assert worker["command"] == ["dask", "worker", address]
    assert wargs[wargs.index("--nthreads") + 1] == "1" and int(wargs[wargs.index("--nworkers") + 1]) >= 1
    assert "volumeMounts" not in worker, "workers ship episodes back: no shared volume"
