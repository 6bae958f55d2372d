"""The KubeRay example (deploy/kuberay/raycluster.yaml) holds to what the lab needs of a
cluster: no Kubernetes runs here, so these are its promises read from the file. (It was
also checked against KubeRay's RayCluster schema, ray.io/v1, once by hand: not here, the
schema is most of a megabyte.)"""

from __future__ import annotations

import json
import tomllib
from pathlib import Path
from typing import Any

import yaml

import labd
from labd.cluster import RESOURCE

ROOT = Path(__file__).resolve().parent.parent
EXAMPLE = ROOT / "deploy" / "kuberay" / "raycluster.yaml"
DATA = tomllib.loads((ROOT / "deploy" / "labd.toml").read_text())["serve"]["data"]


def example() -> dict[str, Any]:
    [cluster] = list(yaml.safe_load_all(EXAMPLE.read_text()))
    assert (cluster["apiVersion"], cluster["kind"]) == ("ray.io/v1", "RayCluster")
    return dict(cluster)


def containers(group: dict[str, Any]) -> list[dict[str, Any]]:
    return list(group["template"]["spec"]["containers"])


def test_its_ray_and_its_image_are_the_labs():
    """The cluster's Ray is the one labd[cluster] pins (Ray pickles across them), and
    its pods run this version's image."""
    spec = example()["spec"]
    extras = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]
    [pin] = extras["optional-dependencies"]["cluster"]
    assert pin == f"ray=={spec['rayVersion']}"
    groups = [spec["headGroupSpec"], *spec["workerGroupSpecs"]]
    images = {c["image"] for g in groups for c in containers(g)}
    assert images and all(i.endswith(f"/labd:{labd.__version__}") for i in images), images


def test_the_head_runs_no_trial_and_every_pod_authenticates():
    spec = example()["spec"]
    head = spec["headGroupSpec"]["rayStartParams"]
    assert head["num-cpus"] == "0" and head["include-dashboard"] == "false"
    for group in [spec["headGroupSpec"], *spec["workerGroupSpecs"]]:
        for container in containers(group):
            env = {e["name"]: e for e in container["env"]}
            assert env["RAY_AUTH_MODE"]["value"] == "token", container["name"]
            assert "secretKeyRef" in env["RAY_AUTH_TOKEN"]["valueFrom"], container["name"]


def test_each_worker_pod_offers_a_slot_a_core_and_can_sandbox():
    """A worker group's ``labd_sim`` slots are its CPUs (one trial a core), and its pods
    run as root with what bubblewrap needs (namespaces, leased uids)."""
    for group in example()["spec"]["workerGroupSpecs"]:
        params = group["rayStartParams"]
        # KubeRay passes the value to `ray start --resources` as it is: a quoted JSON text
        offered = json.loads(json.loads(params["resources"]))
        assert offered == {RESOURCE: int(params["num-cpus"])}, params
        for container in containers(group):
            limits = container["resources"]["limits"]
            assert int(limits["cpu"]) == int(params["num-cpus"]), container["name"]
            context = container["securityContext"]
            assert context["runAsUser"] == 0 and context["privileged"] is True, context
            # a node runs trials under the lab's data folder's path (NodeSetup.work)
            mounts = {m["mountPath"] for m in container["volumeMounts"]}
            assert DATA in mounts, mounts
