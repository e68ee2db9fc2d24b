"""deploy/k8s/ holds valid Kubernetes objects (checked against the Kubernetes 1.32 schemas,
strictly: an unknown field fails, by kubernetes-validate, which ships the schemas, so no
cluster and no network are needed) and the shape scale-out needs for each role: a
Deployment with readiness and liveness probes and a preStop drain, a headless Service, a
Secret for the TLS files, a PodDisruptionBudget. They are validated here, not run."""

from __future__ import annotations

import pathlib

import pytest
import yaml

ROOT = pathlib.Path(__file__).resolve().parent.parent / "deploy" / "k8s"
K8S_VERSION = "1.32.0"  # the Kubernetes release whose schemas the manifests must meet
ROLES = {"evaluator": 7000, "garbler": 7001}


def _validator():
    """kubernetes_validate.utils, or a skip that says why (its schemas ship inside it)."""
    try:
        from kubernetes_validate import utils
    except ImportError:
        pytest.skip("kubernetes-validate is not installed (pip install -e '.[test]')")
    try:
        utils.validate({"apiVersion": "v1", "kind": "ConfigMap",
                        "metadata": {"name": "probe"}}, K8S_VERSION, strict=True)
    except utils.SchemaNotFoundError as exc:
        pytest.skip(f"kubernetes-validate has no offline schemas for Kubernetes "
                    f"{K8S_VERSION}: {exc}")
    return utils


def _objects(role: str) -> dict[str, dict]:
    docs = [d for d in yaml.safe_load_all((ROOT / f"{role}.yaml").read_text()) if d]
    return {d["kind"]: d for d in docs}


@pytest.mark.parametrize("role", ROLES)
def test_every_object_meets_the_kubernetes_schemas(role):
    utils = _validator()
    objects = _objects(role)
    assert set(objects) == {"Secret", "Service", "Deployment", "PodDisruptionBudget"}
    for kind, obj in objects.items():
        try:
            utils.validate(obj, K8S_VERSION, strict=True)
        except utils.ValidationError as exc:
            pytest.fail(f"{role}.yaml {kind}: {exc.message} at {list(exc.path)}")


def test_a_wrong_field_is_caught():
    """The check has teeth: a misspelt field fails it."""
    utils = _validator()
    deployment = _objects("garbler")["Deployment"]
    deployment["spec"]["template"]["spec"]["containers"][0]["readynessProbe"] = {}
    with pytest.raises(utils.ValidationError):
        utils.validate(deployment, K8S_VERSION, strict=True)


@pytest.mark.parametrize("role", ROLES)
def test_each_role_scales_out_behind_a_headless_service_and_drains(role):
    objects = _objects(role)
    service, deployment = objects["Service"], objects["Deployment"]
    assert service["spec"]["clusterIP"] == "None"  # DNS answers with every replica
    assert service["spec"]["selector"] == deployment["spec"]["selector"]["matchLabels"]
    assert objects["PodDisruptionBudget"]["spec"]["selector"]["matchLabels"] == \
        service["spec"]["selector"]
    spec = deployment["spec"]
    assert spec["replicas"] >= 2
    assert spec["strategy"]["rollingUpdate"] == {"maxSurge": 1, "maxUnavailable": 0}
    pod = spec["template"]["spec"]
    (container,) = pod["containers"]
    args = container["args"]
    grace = float(args[args.index("--grace") + 1])
    pre_stop = float(container["lifecycle"]["preStop"]["exec"]["command"][-1])
    assert pod["terminationGracePeriodSeconds"] > pre_stop + grace
    health = ["snail-client", "-q", "health", role, f"127.0.0.1:{ROLES[role]}"]
    for probe in ("readinessProbe", "livenessProbe", "startupProbe"):
        assert container[probe]["exec"]["command"][:5] == health
    # the TLS files come from the Secret, mounted read-only; nothing in the environment
    secret = objects["Secret"]["metadata"]["name"]
    assert {"name": "tls", "secret": {"secretName": secret, "defaultMode": 0o400}} in \
        pod["volumes"]
    assert {"name": "tls", "mountPath": "/tls", "readOnly": True} in container["volumeMounts"]
    assert args[args.index("--tls-dir") + 1] == "/tls"
    assert all("key" not in str(e).lower() for e in container.get("env", []))
    assert set(objects["Secret"]["stringData"]) == {"ca.pem", f"{role}.pem", f"{role}.key"}


def test_the_garbler_dials_the_evaluators_service():
    args = _objects("garbler")["Deployment"]["spec"]["template"]["spec"]["containers"][0][
        "args"]
    evaluator = _objects("evaluator")["Service"]
    assert args[args.index("--evaluator") + 1] == \
        f"{evaluator['metadata']['name']}:{ROLES['evaluator']}"
