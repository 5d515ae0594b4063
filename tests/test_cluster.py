"""The files under ``cluster/``: they parse, they validate, and they say what the docs say they do.

- Launcher YAMLs go through Ray's own launcher preparation and JSON-schema validation (what ``ray up``
  runs before it touches a machine), plus our rules: the package is installed, token auth is on, the
  dashboard binds 127.0.0.1.
- KubeRay manifests are checked against the fields of KubeRay's ``ray.io/v1`` CRDs that we use,
  written out below from the CRD (ray-operator/config/crd/bases, ray-operator/apis/ray/v1), plus the
  operator's own admission rules for those fields (ray-operator/controllers/ray/utils/validation.go).
- ``runtime_env.yaml`` excludes the local state and is accepted by Ray's ``RuntimeEnv``.
- The RayJob's entrypoint is a command line the sweep runner accepts, for a spec and profile that exist.
"""

from __future__ import annotations

import re
import shlex
from pathlib import Path
from typing import Any

import pytest
import yaml

ROOT = Path(__file__).resolve().parents[1]
CLUSTER = ROOT / "cluster"
LAUNCHERS = {"aws-gpu.yaml": "aws", "onprem.yaml": "local"}


def _docs(path: Path) -> list[dict]:
    return [d for d in yaml.safe_load_all(path.read_text()) if d is not None]


def _all_yaml() -> list[Path]:
    return sorted(CLUSTER.rglob("*.yaml"))


def test_every_yaml_under_cluster_parses():
    files = _all_yaml()
    # The set the README documents; a new file must be added here (and there) on purpose.
    assert {p.relative_to(CLUSTER).as_posix() for p in files} == {
        "aws-gpu.yaml", "onprem.yaml", "runtime_env.yaml",
        "kuberay/raycluster.yaml", "kuberay/rayjob.yaml", "kuberay/mlflow.yaml", "kuberay/shared-storage.yaml",
    }
    for path in files:
        docs = _docs(path)
        assert docs and all(isinstance(d, dict) for d in docs), path


# --- Ray cluster launcher ---------------------------------------------------------------------


def _start_commands(config: dict) -> str:
    return "\n".join(config["head_start_ray_commands"] + config["worker_start_ray_commands"])


@pytest.mark.parametrize("name", sorted(LAUNCHERS))
def test_launcher_yaml_passes_rays_own_validation(name):
    from ray.autoscaler._private.util import prepare_config, validate_config

    raw = _docs(CLUSTER / name)[0]
    assert raw["cluster_name"] and raw["provider"]["type"] == LAUNCHERS[name]
    prepared = prepare_config(raw)  # merges Ray's provider defaults, as `ray up` does
    validate_config(prepared)  # raises jsonschema.ValidationError on an unknown or mistyped field
    assert prepared["head_node_type"] in prepared["available_node_types"]


@pytest.mark.parametrize("name", sorted(LAUNCHERS))
def test_launcher_installs_the_package_and_starts_ray_securely(name):
    config = _docs(CLUSTER / name)[0]
    setup = "\n".join(config["setup_commands"])
    # The repository is synced to ~/cdm-lab and installed from there, torch pinned first (README).
    assert config["file_mounts"]["~/cdm-lab"] == "."
    assert setup.index("pip install -q torch==2.13.0") < setup.index("pip install -q -e ~/cdm-lab")
    assert '"ray[default]==2.60.0"' in setup  # the dashboard and job API need ray[default]
    # Anchored at the repository root: a bare "data" would also skip the cdm/data/ package.
    assert {"/.venv", "/.git", "/mlflow.db", "/results", "/data"} <= set(config["rsync_exclude"])
    # Token auth on every node, with the token synced from the user's machine.
    assert config["file_mounts"]["~/.ray/auth_token"] == "~/.ray/auth_token"
    starts = [c for c in config["head_start_ray_commands"] + config["worker_start_ray_commands"] if "ray start" in c]
    assert len(starts) == 2 and all("RAY_AUTH_MODE=token ray start" in c for c in starts)
    head = next(c for c in config["head_start_ray_commands"] if "ray start" in c)
    assert "--dashboard-host=127.0.0.1" in head and "0.0.0.0" not in _start_commands(config)
    # MLflow runs on the head, on its private address, never on all interfaces.
    mlflow = next(c for c in config["head_start_ray_commands"] if "mlflow server" in c)
    host = re.search(r"--host (\S+)", mlflow).group(1)
    assert host not in ("0.0.0.0", "::")


def test_aws_launcher_has_gpu_workers_and_autoscaling_bounds():
    config = _docs(CLUSTER / "aws-gpu.yaml")[0]
    types = config["available_node_types"]
    assert config["head_node_type"] == "head" and types["head"]["resources"] == {"CPU": 0}
    gpu = types["gpu_worker"]
    assert gpu["node_config"]["InstanceType"].startswith(("g5.", "g6.", "p4", "p5"))
    assert 1 <= gpu["min_workers"] <= gpu["max_workers"] <= config["max_workers"]
    # The README's one-liner replaces this marker with the region's Deep Learning AMI.
    assert {t["node_config"]["ImageId"] for t in types.values()} == {"ami-REPLACE_WITH_DLAMI"}
    assert "ami-REPLACE_WITH_DLAMI" in (CLUSTER / "README.md").read_text()


def test_onprem_launcher_names_the_private_interface_everywhere():
    config = _docs(CLUSTER / "onprem.yaml")[0]
    provider = config["provider"]
    assert provider["head_ip"] and len(provider["worker_ips"]) >= 1
    head_ip = provider["head_ip"]
    head_cmds = "\n".join(config["head_start_ray_commands"])
    # The head advertises, and MLflow binds, the head_ip the launcher connects to.
    assert f"--node-ip-address={head_ip}" in head_cmds and f"mlflow server --host {head_ip}" in head_cmds
    assert config["min_workers"] == config["max_workers"] == len(provider["worker_ips"])


# --- KubeRay ----------------------------------------------------------------------------------
# The fields we use, as KubeRay's ray.io/v1 CRD types them. A schema node is a python type, a dict
# {key: node} (keys ending in "?" optional, others required; unknown keys are errors, since the
# operator's API server prunes them silently), or a list [node] for arrays. Pod templates are
# Kubernetes' own PodTemplateSpec, checked only where KubeRay requires something of them.

_STR_MAP = "map[str]str"  # additionalProperties: {type: string} (rayStartParams values must be strings)
_POD_TEMPLATE = "PodTemplateSpec"

HEAD_GROUP = {"rayStartParams?": _STR_MAP, "template": _POD_TEMPLATE, "serviceType?": str}
WORKER_GROUP = {
    "groupName": str, "minReplicas": int, "maxReplicas": int, "replicas?": int,
    "rayStartParams?": _STR_MAP, "template": _POD_TEMPLATE,
}
RAY_CLUSTER_SPEC = {
    "rayVersion?": str,
    "enableInTreeAutoscaling?": bool,
    "authOptions?": {"mode?": str},
    "headGroupSpec": HEAD_GROUP,
    "workerGroupSpecs?": [WORKER_GROUP],
}
RAY_JOB_SPEC = {
    "entrypoint": str,
    "runtimeEnvYAML?": str,
    "submissionMode?": str,
    "backoffLimit?": int,
    "shutdownAfterJobFinishes?": bool,
    "ttlSecondsAfterFinished?": int,
    "rayClusterSpec": RAY_CLUSTER_SPEC,
}
METADATA = {"name": str, "labels?": _STR_MAP}
KUBERAY_KINDS = {
    "RayCluster": {"apiVersion": str, "kind": str, "metadata": METADATA, "spec": RAY_CLUSTER_SPEC},
    "RayJob": {"apiVersion": str, "kind": str, "metadata": METADATA, "spec": RAY_JOB_SPEC},
}


def _check(node: Any, value: Any, path: str) -> list[str]:
    """Errors of ``value`` against schema ``node`` (see above), each naming its path."""
    if node == _STR_MAP:
        ok = isinstance(value, dict) and all(isinstance(k, str) and isinstance(v, str) for k, v in value.items())
        return [] if ok else [f"{path}: must map strings to strings (quote numbers and booleans)"]
    if node == _POD_TEMPLATE:
        containers = (value or {}).get("spec", {}).get("containers")
        if not containers:
            return [f"{path}.spec.containers: at least one container"]
        return [f"{path}.spec.containers[{i}]: needs name and image" for i, c in enumerate(containers)
                if not (c.get("name") and c.get("image"))]
    if isinstance(node, list):
        if not isinstance(value, list):
            return [f"{path}: must be a list"]
        return [e for i, item in enumerate(value) for e in _check(node[0], item, f"{path}[{i}]")]
    if isinstance(node, dict):
        if not isinstance(value, dict):
            return [f"{path}: must be a mapping"]
        keys = {k.rstrip("?"): k for k in node}
        errors = [f"{path}.{k}: unknown field" for k in value if k not in keys]
        errors += [f"{path}.{k}: required" for k, spec in keys.items() if not spec.endswith("?") and k not in value]
        return errors + [e for k, v in value.items() if k in keys for e in _check(node[keys[k]], v, f"{path}.{k}")]
    # bool is an int in Python; the CRD keeps them apart.
    ok = isinstance(value, node) and not (node is int and isinstance(value, bool))
    return [] if ok else [f"{path}: must be {node.__name__}, got {type(value).__name__}"]


def _operator_rules(spec: dict, path: str) -> list[str]:
    """The KubeRay operator's admission rules (validation.go) for the RayCluster fields we set."""
    errors = []
    for group in spec.get("workerGroupSpecs", []):
        lo, hi, n = group["minReplicas"], group["maxReplicas"], group.get("replicas", group["minReplicas"])
        if not 0 <= lo <= n <= hi:
            errors.append(
                f"{path}.workerGroupSpecs[{group['groupName']}]: need 0 <= minReplicas <= replicas <= maxReplicas"
            )
    mode = spec.get("authOptions", {}).get("mode", "token" if "authOptions" in spec else "disabled")
    if mode not in ("disabled", "token"):
        errors.append(f"{path}.authOptions.mode: disabled or token")
    if mode == "token":
        version = tuple(int(x) for x in spec.get("rayVersion", "0").split(".")[:3])
        if version < (2, 52, 0):
            errors.append(f"{path}.rayVersion: token auth needs Ray >= 2.52.0")
    return errors


def _kuberay_objects() -> list[tuple[str, dict]]:
    return [(f"{p.name}#{i}", d) for p in sorted((CLUSTER / "kuberay").glob("*.yaml"))
            for i, d in enumerate(_docs(p)) if d.get("apiVersion", "").startswith("ray.io/")]


def test_kuberay_manifests_match_the_crd_fields_we_use():
    objects = _kuberay_objects()
    assert sorted(d["kind"] for _, d in objects) == ["RayCluster", "RayJob"]
    for where, doc in objects:
        assert doc["apiVersion"] == "ray.io/v1", where
        errors = _check(KUBERAY_KINDS[doc["kind"]], doc, doc["kind"])
        spec = doc["spec"] if doc["kind"] == "RayCluster" else doc["spec"]["rayClusterSpec"]
        errors += _operator_rules(spec, where)
        # RayCluster names are DNS-1035 labels of <= 53 characters; RayJob names 6 fewer.
        limit = 53 if doc["kind"] == "RayCluster" else 47
        if (
            not re.fullmatch(r"[a-z]([-a-z0-9]*[a-z0-9])?", doc["metadata"]["name"])
            or len(doc["metadata"]["name"]) > limit
        ):
            errors.append(f"{where}: metadata.name must be a DNS-1035 label of <= {limit} characters")
        assert not errors, "\n".join(errors)


def test_the_schema_checker_catches_what_the_operator_would_reject():
    # Guards the checker itself: each mistake below is one KubeRay would reject or silently drop.
    good = _docs(CLUSTER / "kuberay" / "raycluster.yaml")[0]
    bad_types = {**good["spec"], "headGroupSpec": {**good["spec"]["headGroupSpec"], "rayStartParams": {"num-cpus": 0}}}
    assert any("strings to strings" in e for e in _check(RAY_CLUSTER_SPEC, bad_types, "spec"))
    typo = {**good["spec"], "workerGroupSpec": []}
    assert any("workerGroupSpec: unknown field" in e for e in _check(RAY_CLUSTER_SPEC, typo, "spec"))
    worker = {**good["spec"]["workerGroupSpecs"][0], "minReplicas": 9}
    assert _operator_rules({**good["spec"], "workerGroupSpecs": [worker]}, "spec")
    assert _operator_rules({**good["spec"], "rayVersion": "2.40.0"}, "spec")


def test_kuberay_pods_use_token_auth_shared_storage_and_reach_mlflow():
    mlflow = {d["kind"]: d for d in _docs(CLUSTER / "kuberay" / "mlflow.yaml")}
    assert set(mlflow) == {"PersistentVolumeClaim", "Deployment", "Service", "NetworkPolicy"}
    assert mlflow["Service"]["spec"]["type"] == "ClusterIP"  # never LoadBalancer or NodePort
    assert mlflow["Deployment"]["spec"]["strategy"]["type"] == "Recreate"  # one SQLite writer
    pod = mlflow["Deployment"]["spec"]["template"]["spec"]
    args = pod["containers"][0]["command"]
    mount = pod["containers"][0]["volumeMounts"][0]
    assert (
        pod["volumes"][0]["persistentVolumeClaim"]["claimName"] == mlflow["PersistentVolumeClaim"]["metadata"]["name"]
    )
    # Both stores on the volume.
    assert f"--backend-store-uri=sqlite:///{mount['mountPath']}/mlflow.db" in args
    assert f"--artifacts-destination={mount['mountPath']}/artifacts" in args
    client_label = mlflow["NetworkPolicy"]["spec"]["ingress"][0]["from"][0]["podSelector"]["matchLabels"]
    shared = _docs(CLUSTER / "kuberay" / "shared-storage.yaml")[0]
    assert shared["spec"]["accessModes"] == ["ReadWriteMany"]
    for where, doc in _kuberay_objects():
        spec = doc["spec"] if doc["kind"] == "RayCluster" else doc["spec"]["rayClusterSpec"]
        assert spec["authOptions"]["mode"] == "token", where
        assert spec["headGroupSpec"]["serviceType"] == "ClusterIP", where
        for group in [spec["headGroupSpec"], *spec["workerGroupSpecs"]]:
            assert group["template"]["metadata"]["labels"].items() >= client_label.items(), where
            vols = {v["name"]: v for v in group["template"]["spec"]["volumes"]}
            assert vols["shared"]["persistentVolumeClaim"]["claimName"] == shared["metadata"]["name"], where
            assert {"name": "shared", "mountPath": "/mnt/shared"} in group["template"]["spec"]["containers"][0][
                "volumeMounts"
            ]
        gpu = spec["workerGroupSpecs"][0]["template"]["spec"]["containers"][0]["resources"]["limits"]
        assert gpu["nvidia.com/gpu"] == "1", where


def test_rayjob_entrypoint_is_a_valid_paper_sweep(capsys, tmp_path, monkeypatch):
    from sweeps import run
    from tests.input_fixtures import paper_inputs

    job = _docs(CLUSTER / "kuberay" / "rayjob.yaml")[0]["spec"]
    argv = shlex.split(job["entrypoint"])
    assert argv[:2] == ["python", "/home/ray/cdm-lab/sweeps/run.py"]
    args = run.build_parser().parse_args(argv[2:])
    assert (args.profile, args.address) == ("paper", "auto")
    assert str(args.storage).startswith("/mnt/shared/") and args.tracking_uri == "http://cdm-mlflow:5000"
    assert yaml.safe_load(job["runtimeEnvYAML"]) == {
        "env_vars": {"PYTHONUNBUFFERED": "1", "CDM_INPUTS": "/mnt/shared/cdm_inputs"}
    }
    # The image holds the repository at /home/ray/cdm-lab (cluster/Dockerfile): map the spec path
    # back here and let the runner expand it with the paper profile, as it will in the job.
    spec = ROOT / Path(args.spec).relative_to("/home/ray/cdm-lab")
    monkeypatch.setenv("CDM_INPUTS", str(paper_inputs(tmp_path / "inputs")))  # the paper profile's ViT weights
    assert run.main([str(spec), "--profile", "paper", "--address", "auto", "--dry-run"]) == 0
    out = capsys.readouterr().out
    assert "profile paper" in out and "1 Train workers, 4 CPUs + 1 GPUs per worker" in out
    assert "/home/ray/cdm-lab" in (CLUSTER / "Dockerfile").read_text()


# --- runtime_env.yaml -------------------------------------------------------------------------

def test_runtime_env_excludes_local_state_and_ray_accepts_it():
    from ray.runtime_env import RuntimeEnv

    env = _docs(CLUSTER / "runtime_env.yaml")[0]
    assert env["working_dir"] == "."
    assert {"/.venv", "/mlflow.db", "/mlruns", "/results", "/data", "/.git"} <= set(env["excludes"])
    parsed = RuntimeEnv(**env)  # Ray's own validation of the fields and their types
    assert parsed.working_dir() == "." and parsed.env_vars() == {
        "PYTHONUNBUFFERED": "1",
        "CDM_INPUTS": "/mnt/shared/cdm_inputs",
    }


def test_runtime_env_excludes_match_what_ray_would_upload(tmp_path):
    # Ray's own matcher for `excludes`, applied to a tree like a used checkout: local state stays home.
    from ray._private.runtime_env.packaging import _get_excludes

    env = _docs(CLUSTER / "runtime_env.yaml")[0]
    for rel in (".venv/bin/python", "mlflow.db", "mlruns/0/meta.yaml", "results/point_size/smoke/sweep.json",
                "data/shapes/a.obj", ".git/HEAD", "cdm/train.py", "sweeps/run.py", "cdm/__pycache__/x.pyc",
                "cdm/data/procedural.py", "tests/data/golden.pt"):
        (tmp_path / rel).parent.mkdir(parents=True, exist_ok=True)
        (tmp_path / rel).write_text("x")
    excluded = _get_excludes(tmp_path, env["excludes"])
    uploaded = {p.relative_to(tmp_path).as_posix() for p in tmp_path.rglob("*") if p.is_file()
                and not any(excluded(q) for q in [p, *p.parents] if q != tmp_path and tmp_path in q.parents)}
    assert uploaded == {"cdm/train.py", "sweeps/run.py", "cdm/data/procedural.py"}
