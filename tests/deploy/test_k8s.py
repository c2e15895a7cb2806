"""deploy/k8s: valid Kubernetes objects, and each container starts its daemon with the settings
the compose service of the same role gives it, as the daemons' own parsers read them."""

from __future__ import annotations

import copy
import re
import shutil
import subprocess
from pathlib import Path

import kubernetes_validate
import pytest
import zenoh
from ruamel.yaml import YAML

from l2r.router import parser as router_parser

from . import compose
from .daemons import SECRETS, WRITES_TO, daemon_settings, healthcheck_args
from .zenoh_helpers import DEPLOY

K8S = DEPLOY / "k8s"
# The oldest release the manifests need (a StatefulSet pod's index as a label came in 1.28) and
# the newest kubernetes-validate knows.
KUBERNETES_VERSIONS = ("1.28", kubernetes_validate.latest_version())
POD_INDEX = "metadata.labels['apps.kubernetes.io/pod-index']"
ROLES = ("replay", "learner", "actor")
KEPT_ON = {"replay": "volumeClaimTemplate", "learner": "persistentVolumeClaim", "actor": "emptyDir"}
"""role -> the kind of volume its daemon writes to"""


def load_all(text: str) -> list[dict]:
    return [doc for doc in YAML(typ="safe").load_all(text) if doc]


def kustomization(overlay: str) -> dict:
    return YAML(typ="safe").load((K8S / overlay / "kustomization.yaml").read_text())


def base_objects() -> list[dict]:
    """The objects of deploy/k8s/base, from the files its kustomization lists (no kubectl needed)."""
    return [doc for name in kustomization("base")["resources"] for doc in load_all((K8S / "base" / name).read_text())]


def kubectl(*args: str) -> str:
    """What ``kubectl ARGS`` prints; only commands that need no cluster."""
    if not shutil.which("kubectl"):
        pytest.skip("needs kubectl")
    done = subprocess.run(["kubectl", *args], capture_output=True, text=True, timeout=60)
    assert done.returncode == 0, done.stderr
    return done.stdout


def kustomize(overlay: str) -> list[dict]:
    """What ``kubectl apply -k deploy/k8s/<overlay>`` would apply."""
    return load_all(kubectl("kustomize", str(K8S / overlay)))


def find(objects: list[dict], kind: str, name: str) -> dict:
    (found,) = [o for o in objects if o["kind"] == kind and o["metadata"]["name"] == name]
    return found


def workload(objects: list[dict], role: str) -> dict:
    (found,) = [o for o in objects if o["kind"] in ("Deployment", "StatefulSet") and o["metadata"]["name"] == role]
    return found


def container(objects: list[dict], role: str) -> dict:
    (found,) = workload(objects, role)["spec"]["template"]["spec"]["containers"]
    return found


def environment(objects: list[dict], role: str, pod_index: int) -> dict[str, str]:
    """The environment of ``role``'s container in pod ``pod_index``: its ConfigMaps, then its own variables."""
    spec = container(objects, role)
    env = {}
    for source in spec.get("envFrom", []):
        env |= find(objects, "ConfigMap", source["configMapRef"]["name"])["data"]
    for variable in spec.get("env", []):
        if "value" in variable:
            env[variable["name"]] = variable["value"]
        else:
            assert variable["valueFrom"]["fieldRef"]["fieldPath"] == POD_INDEX, variable
            env[variable["name"]] = str(pod_index)
    return env


def volumes(objects: list[dict], role: str) -> dict[str, tuple[str, dict]]:
    """Where ``role``'s container mounts each of its volumes: path -> (kind of volume, its spec)."""
    pod = workload(objects, role)["spec"]
    by_name = {}
    for volume in pod["template"]["spec"].get("volumes", []):
        (kind,) = volume.keys() - {"name"}
        by_name[volume["name"]] = (kind, volume[kind])
    for claim in pod.get("volumeClaimTemplates", []):
        by_name[claim["metadata"]["name"]] = ("volumeClaimTemplate", claim["spec"])
    return {m["mountPath"]: by_name[m["name"]] for m in container(objects, role)["volumeMounts"]}


def pod_settings(objects: list[dict], role: str, secrets: Path, pod_index: int = 0, **environ: str):
    """The settings ``role``'s daemon starts with in pod ``pod_index``, its role's keys mounted."""
    spec = container(objects, role)
    env = environment(objects, role, pod_index) | environ
    return daemon_settings(spec["command"] + spec["args"], env, {SECRETS: secrets / role})


def test_the_kustomization_lists_every_manifest():
    listed = kustomization("base")["resources"]
    assert sorted(listed) == sorted(p.name for p in (K8S / "base").glob("*.yaml") if p.name != "kustomization.yaml")


@pytest.mark.parametrize("version", KUBERNETES_VERSIONS)
def test_every_manifest_follows_the_kubernetes_schemas(version):
    objects = base_objects()
    for obj in objects:
        kubernetes_validate.validate(obj, version, strict=True)
    broken = copy.deepcopy(workload(objects, "replay"))
    broken["spec"]["template"]["spec"]["containers"][0]["readinesProbe"] = {}  # a typo the schema must catch
    with pytest.raises(kubernetes_validate.ValidationError):
        kubernetes_validate.validate(broken, version, strict=True)


@pytest.mark.parametrize("overlay", ["base", "gpu"])
def test_kustomize_renders_valid_objects(overlay):
    for obj in kustomize(overlay):
        kubernetes_validate.validate(obj, KUBERNETES_VERSIONS[-1], strict=True)


def test_selectors_select_their_own_pods():
    objects = base_objects()
    for role in ("router", *ROLES):
        pod = workload(objects, role)
        labels = pod["spec"]["template"]["metadata"]["labels"]
        assert pod["spec"]["selector"]["matchLabels"].items() <= labels.items(), role
        others = [workload(objects, r)["spec"]["template"]["metadata"]["labels"] for r in ROLES if r != role]
        assert not any(pod["spec"]["selector"]["matchLabels"].items() <= o.items() for o in others), role
    for service in ("router", "replay"):
        selector = find(objects, "Service", service)["spec"]["selector"]
        assert selector.items() <= workload(objects, service)["spec"]["template"]["metadata"]["labels"].items()


@pytest.mark.parametrize("role", ROLES)
def test_each_daemon_starts_with_the_settings_compose_gives_it(role, rendered_secrets):
    """Pod 0 of each role runs its daemon, and its health check, as the compose service does."""
    objects = base_objects()
    service = compose.services({})[role]
    mounts = {SECRETS: rendered_secrets / role}
    assert pod_settings(objects, role, rendered_secrets) == daemon_settings(service.command, {}, mounts)
    probe = container(objects, role)["readinessProbe"]["exec"]["command"]
    assert healthcheck_args(probe, environment(objects, role, 0), mounts) == \
        healthcheck_args(service.healthcheck, {}, mounts)
    grace = workload(objects, role)["spec"]["template"]["spec"]["terminationGracePeriodSeconds"]
    assert grace == compose.seconds(compose.load()["services"][role]["stop_grace_period"])


@pytest.mark.parametrize("role", ROLES)
def test_each_daemon_reads_its_role_secret_and_writes_to_its_volume(role, rendered_secrets):
    objects = base_objects()
    settings = pod_settings(objects, role, rendered_secrets)
    mounted = volumes(objects, role)
    assert mounted[SECRETS] == ("secret", {"secretName": f"l2r-{role}", "defaultMode": 0o440})
    assert settings.zenoh_config == rendered_secrets / role / "zenoh.json5"
    written = Path(getattr(settings, WRITES_TO[role]))
    kinds = [kind for path, (kind, _) in mounted.items() if Path(path) in (written, *written.parents)]
    assert kinds == [KEPT_ON[role]], f"{written} is on {kinds}"
    # The daemons run as the images' user, who can read the keys (group) and write the volumes.
    security = workload(objects, role)["spec"]["template"]["spec"]["securityContext"]
    assert security["runAsUser"] == 1000 and security["fsGroup"] == 1000


def test_replay_pod_k_is_shard_k_of_as_many_as_the_actors_feed(rendered_secrets):
    objects = base_objects()
    replicas = workload(objects, "replay")["spec"]["replicas"]
    assert workload(objects, "replay")["kind"] == "StatefulSet"
    assert find(objects, "ConfigMap", "l2r-run")["data"]["L2R_NUM_SHARDS"] == str(replicas)
    assert pod_settings(objects, "actor", rendered_secrets).num_shards == replicas
    for k in range(3):  # scaled to three shards, with L2R_NUM_SHARDS raised alongside
        shard = pod_settings(objects, "replay", rendered_secrets, pod_index=k, L2R_NUM_SHARDS="3")
        assert (shard.shard, shard.num_shards) == (k, 3)


def test_actors_are_replicas_that_ask_replay_shard_0_for_their_ids(rendered_secrets):
    objects = base_objects()
    assert workload(objects, "actor")["kind"] == "Deployment" and workload(objects, "actor")["spec"]["replicas"] >= 1
    assert pod_settings(objects, "actor", rendered_secrets).actor_id == "auto"
    assert pod_settings(objects, "replay", rendered_secrets, pod_index=0).snapshot_dir is not None


def test_router_serves_the_endpoint_in_the_daemons_configs():
    objects = base_objects()
    router = container(objects, "router")
    compose_router = compose.load()["services"]["router"]
    assert (router["image"], router["args"]) == (compose_router["image"], compose_router["command"])
    config = Path(router_parser().parse_args(router["args"]).zenoh_config)
    assert volumes(objects, "router")[str(config.parent)] == ("secret", {"secretName": "l2r-router",
                                                                          "defaultMode": 0o444})
    (port,) = find(objects, "Service", "router")["spec"]["ports"]
    (container_port,) = router["ports"]
    assert port["targetPort"] == container_port["name"] == router["readinessProbe"]["tcpSocket"]["port"]
    for role in ROLES:
        template = zenoh.Config.from_json5((DEPLOY / "zenoh" / f"{role}.json5").read_text())
        assert template.get_json("connect/endpoints") == f'["tls/router:{port["port"]}"]', role


@pytest.mark.parametrize("role", ("router", *ROLES))
def test_the_secret_made_as_docs_deploy_md_says_holds_every_file_its_role_reads(role, rendered_secrets):
    """kubectl create secret generic l2r-<role> --from-file=deploy/secrets/<role>/: a key per file,
    among them every file the role's Zenoh config names where the pod mounts the Secret."""
    made = kubectl("create", "secret", "generic", f"l2r-{role}", f"--from-file={rendered_secrets / role}/",
                   "--dry-run=client", "-o", "yaml")
    (secret,) = load_all(made)
    kubernetes_validate.validate(secret, KUBERNETES_VERSIONS[-1], strict=True)
    config = (rendered_secrets / role / "zenoh.json5").read_text()
    named = set(re.findall(re.escape(SECRETS) + r"/([\w.]+)", config))
    assert {"ca.pem", "cert.pem", "key.pem"} <= named <= secret["data"].keys()
    assert "zenoh.json5" in secret["data"]
    assert volumes(base_objects(), role)[SECRETS][1]["secretName"] == secret["metadata"]["name"]


def test_gpu_overlay_puts_the_learner_on_a_gpu_and_changes_nothing_else():
    base, gpu = kustomize("base"), kustomize("gpu")
    learner = container(gpu, "learner")
    assert learner["resources"].pop("limits") == {"nvidia.com/gpu": 1}
    assert learner.pop("image") == compose.load()["services"]["learner-gpu"]["image"]
    del container(base, "learner")["image"]
    assert gpu == base
