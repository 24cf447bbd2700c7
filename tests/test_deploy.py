"""deploy/*.yaml against Kubernetes' own schema, with kubectl's client-side dry run.

``kubectl apply --dry-run=client --validate=strict`` validates each object against the
OpenAPI schema it downloads from the cluster's API server (unknown fields, wrong
types, bad kinds); even a client dry run needs that server. Where kubectl or a
reachable cluster is missing (this CI machine: kubectl is installed, no cluster), the
test is skipped with kubectl's own reason. deploy/'s commands are checked against the
hil command line in tests/harness/test_search.py.
"""

from __future__ import annotations

import shutil
import subprocess
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
MANIFESTS = sorted((ROOT / "deploy").glob("*.yaml"))
# What kubectl says when it has no API server to take the schema from.
_NO_SERVER = ("failed to download openapi", "connection refused", "unable to recognize",
              "couldn't get current server API group list", "no configuration has been provided")


def _kubectl(*args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run(["kubectl", *args], capture_output=True, text=True, timeout=60, cwd=ROOT,
                          stdin=subprocess.DEVNULL)


def test_there_are_manifests_to_validate():
    assert {p.name for p in MANIFESTS} >= {"search-job.yaml", "merge-job.yaml"}


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
    assert kinds and all("." in k or k in {"job", "persistentvolumeclaim"} for k in kinds), p.stdout


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
