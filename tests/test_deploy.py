"""The deployment files (docker-compose.yml, deploy/): `docker-compose config` validates them (Debian's
docker-compose 1.29 from `make sysdeps`; `config` needs no Docker daemon), and their content is checked against
the code: health checks and start order, the Dockerfile's install steps against the Makefile's `install` recipe,
and the environment against the service's settings (services/core/config.py) and subcommands.

No image is built and no container runs here (no Docker daemon on the test machines).
"""

from __future__ import annotations

import os
import re
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path
from typing import Any

import pytest
import yaml

ROOT = Path(__file__).resolve().parents[1]
COMPOSE = ROOT / "docker-compose.yml"
WORKER_COMPOSE = ROOT / "deploy" / "docker-compose.worker.yml"
ENV_EXAMPLE = ROOT / ".env.example"
DOCKER_COMPOSE = shutil.which("docker-compose") or "/usr/bin/docker-compose"
# Environment variables of the service's containers that are not NEUMATEX_ settings: boto3's standard credentials.
NON_SETTINGS_ENV = {"AWS_ACCESS_KEY_ID", "AWS_SECRET_ACCESS_KEY"}
# Variables compose substitutes (`${NAME...}`) that only worker machines set (deploy/.env).
WORKER_ONLY_VARS = {"CENTRAL_HOST"}

needs_compose = pytest.mark.skipif(not Path(DOCKER_COMPOSE).exists(),
                                   reason="docker-compose is not installed (make sysdeps installs it)")


def compose_config(file: Path, *extra: str, env_file: Path | None = None, env: dict[str, str] | None = None
                   ) -> dict[str, Any]:  # fmt: skip
    """`docker-compose [--env-file F] -f FILE [extra...] config`, parsed; fails the test with compose's message.
    Variables that the compose files substitute are removed from the environment first, so only env_file and env
    decide them."""
    clean = {k: v for k, v in os.environ.items() if k not in substituted_vars() and not k.startswith("COMPOSE_")}
    clean.update(env or {})
    if env_file is None:
        env_file = empty_env_file()  # compose then reads no .env: the defaults written in the file apply
    cmd = [DOCKER_COMPOSE, "--env-file", str(env_file), "-f", str(file), *extra, "config"]
    r = subprocess.run(cmd, cwd=ROOT, env=clean, capture_output=True, text=True, timeout=60)
    assert r.returncode == 0, f"{' '.join(cmd)} failed:\n{r.stderr}"
    return yaml.safe_load(r.stdout)


def empty_env_file() -> Path:
    """An empty file for `--env-file` (compose 1.29 refuses /dev/null: "not a file")."""
    path = Path(tempfile.gettempdir()) / "neumatex-test-empty.env"
    path.write_text("")
    return path


def substituted_vars() -> set[str]:
    """Every NAME in `${NAME...}` of the compose files (`$${...}` escapes excluded)."""
    names: set[str] = set()
    for f in (COMPOSE, WORKER_COMPOSE):
        names |= set(re.findall(r"(?<!\$)\$\{([A-Za-z_][A-Za-z0-9_]*)", f.read_text()))
    return names


def env_example_keys() -> set[str]:
    """Keys of .env.example, commented-out assignments (`# KEY=...`) included."""
    keys = set()
    for line in ENV_EXAMPLE.read_text().splitlines():
        m = re.match(r"^#?\s*([A-Z][A-Z0-9_]*)=", line)
        if m:
            keys.add(m.group(1))
    return keys


@pytest.fixture(scope="module")
def main_config() -> dict[str, Any]:
    return compose_config(COMPOSE, "--profile", "gpu")


@pytest.fixture(scope="module")
def worker_config() -> dict[str, Any]:
    return compose_config(WORKER_COMPOSE, "--profile", "gpu", env={"CENTRAL_HOST": "10.0.0.5"})


def app_services(config: dict[str, Any]) -> dict[str, dict[str, Any]]:
    """The services that run the NeuMatEx image (built from deploy/Dockerfile)."""
    return {name: s for name, s in config["services"].items() if "build" in s}


def one_shot(config: dict[str, Any]) -> set[str]:
    """Services others wait on to *finish* (service_completed_successfully): init containers, no health check."""
    return {dep for s in config["services"].values() for dep, cond in (s.get("depends_on") or {}).items()
            if cond.get("condition") == "service_completed_successfully"}  # fmt: skip


# -- compose files validate ------------------------------------------------------------------------------------
@needs_compose
def test_compose_validates_with_and_without_the_gpu_profile() -> None:
    # docker-compose 1.29 (compose spec, profiles since 1.28): `config` checks the file against its schema,
    # interpolates variables and resolves anchors; it lists profiled services either way, so also check the
    # profile is set where it must be.
    expected = {"postgres", "redis", "minio", "minio-init", "proxy", "api", "worker-cpu", "worker-gpu", "beat"}
    plain = compose_config(COMPOSE)
    gpu = compose_config(COMPOSE, "--profile", "gpu")
    example = compose_config(COMPOSE, env_file=ENV_EXAMPLE)
    for config in (plain, gpu, example):
        assert set(config["services"]) == expected
    profiled = {name for name, s in plain["services"].items() if s.get("profiles")}
    assert profiled == {"worker-gpu"} and plain["services"]["worker-gpu"]["profiles"] == ["gpu"]
    # a machine without GPUs can `up` the rest: nothing outside the profile depends on the GPU worker
    for name, s in plain["services"].items():
        assert "worker-gpu" not in (s.get("depends_on") or {}), f"{name} depends on the gpu-profile worker"
    # .env.example holds the defaults the file falls back to: the same configuration
    assert example == plain


@needs_compose
def test_worker_compose_validates_and_needs_the_central_host() -> None:
    config = compose_config(WORKER_COMPOSE, "--profile", "gpu", env={"CENTRAL_HOST": "10.0.0.5"})
    assert set(config["services"]) == {"worker-cpu", "worker-gpu"}
    env = config["services"]["worker-cpu"]["environment"]
    assert "@10.0.0.5:5432/" in env["NEUMATEX_DATABASE_URL"] and "@10.0.0.5:6379/" in env["NEUMATEX_REDIS_URL"]
    assert env["NEUMATEX_S3_ENDPOINT_URL"] == "http://10.0.0.5:9000"
    clean = {k: v for k, v in os.environ.items() if k not in substituted_vars()}
    r = subprocess.run([DOCKER_COMPOSE, "--env-file", str(empty_env_file()), "-f",
                        str(WORKER_COMPOSE), "config"], cwd=ROOT, env=clean, capture_output=True, text=True,
                       timeout=60)  # fmt: skip
    assert r.returncode != 0 and "CENTRAL_HOST" in r.stderr


# -- what the services are -------------------------------------------------------------------------------------
@needs_compose
def test_every_long_running_service_has_a_healthcheck_and_waits_for_healthy_dependencies(
        main_config: dict[str, Any], worker_config: dict[str, Any]) -> None:
    for config in (main_config, worker_config):
        init = one_shot(config)
        for name, s in config["services"].items():
            if name in init:
                assert s.get("restart", "no") == "no", f"{name} runs once and must not restart"
                continue
            check = s.get("healthcheck")
            assert check and check.get("test") and not check.get("disable"), f"{name} has no healthcheck"
            assert s.get("restart") == "unless-stopped", name
            for dep, cond in (s.get("depends_on") or {}).items():
                want = "service_completed_successfully" if dep in init else "service_healthy"
                assert cond.get("condition") == want, f"{name} -> {dep}: {cond}"
    tests = {name: " ".join(s["healthcheck"]["test"]) for name, s in main_config["services"].items()
             if "healthcheck" in s}  # fmt: skip
    assert "/healthz" in tests["api"] and "/healthz" in tests["proxy"]
    assert "redis-cli ping" in tests["redis"]
    assert "pg_isready" in tests["postgres"]
    assert "mc ready" in tests["minio"]
    assert "inspect ping" in tests["worker-cpu"] and "inspect ping" in tests["worker-gpu"]


@needs_compose
def test_services_commands_volumes_and_gpu_reservation(main_config: dict[str, Any]) -> None:
    services = main_config["services"]
    assert services["postgres"]["image"] == "postgres:16"
    assert services["redis"]["image"] == "redis:7" and "--appendonly yes" in " ".join(services["redis"]["command"])
    assert services["minio"]["image"].startswith("minio/minio")
    assert services["minio-init"]["image"].startswith("minio/mc")
    assert "mc mb" in " ".join(services["minio-init"]["command"])
    volumes = {v.split(":")[0] if isinstance(v, str) else v["source"] for name in ("postgres", "redis", "minio")
               for v in services[name]["volumes"]}  # fmt: skip
    assert volumes == {"postgres-data", "redis-data", "minio-data"} <= set(main_config["volumes"])

    api = " ".join(services["api"]["command"])
    assert api.index("python -m services migrate") < api.index("python -m services api --host 0.0.0.0 --port 8000")
    assert services["worker-cpu"]["command"][:5] == ["python", "-m", "services", "worker", "--queue"]
    assert services["worker-cpu"]["command"][5] == "cpu" and services["worker-gpu"]["command"][5] == "gpu"
    beats = [n for n, s in services.items() if s.get("command") and " ".join(s["command"]).endswith("services beat")]
    assert beats == ["beat"], f"exactly one beat process, got {beats}"
    devices = services["worker-gpu"]["deploy"]["resources"]["reservations"]["devices"]
    assert devices == [{"driver": "nvidia", "count": "all", "capabilities": ["gpu"]}]


@needs_compose
def test_the_service_subcommands_compose_runs_exist(main_config: dict[str, Any]) -> None:
    r = subprocess.run([sys.executable, "-m", "services", "--help"], cwd=ROOT, capture_output=True, text=True,
                       timeout=60)  # fmt: skip
    assert r.returncode == 0, r.stderr
    m = re.search(r"\{([a-z,-]+)\}", r.stdout)
    assert m, r.stdout
    available = set(m.group(1).split(","))
    used = set()
    for s in main_config["services"].values():
        used |= set(re.findall(r"python -m services ([a-z-]+)", " ".join(s.get("command") or [])))
    assert used == {"migrate", "api", "worker", "beat"}
    assert used <= available, f"docker-compose.yml runs `python -m services` {sorted(used - available)}, which " \
                              f"services/__main__.py does not have (it has {sorted(available)})"


@needs_compose
def test_the_proxy_and_the_api_agree_on_the_body_files(main_config: dict[str, Any]) -> None:
    # nginx names each upload's body file to the API (deploy/nginx/neumatex.conf.template): both must see the same
    # folder, share the secret, and run as the same user (the files are mode 0600)
    proxy, api = main_config["services"]["proxy"], main_config["services"]["api"]
    template = "deploy/nginx/neumatex.conf.template:/etc/nginx/templates/default.conf.template"
    mounts = {name: {(v["source"], v["target"]) if isinstance(v, dict) else tuple(v.split(":")[:2])
                     for v in s["volumes"]} for name, s in (("proxy", proxy), ("api", api))}  # fmt: skip
    assert any(str(src).endswith(template.split(":")[0]) and dst == template.split(":")[1]
               for src, dst in mounts["proxy"])  # fmt: skip
    body_dir = api["environment"]["NEUMATEX_PROXY_BODY_DIR"]
    assert proxy["environment"]["NEUMATEX_PROXY_BODY_DIR"] == body_dir
    assert ("upload-bodies", body_dir) in mounts["proxy"] and ("upload-bodies", body_dir) in mounts["api"]
    assert proxy["environment"]["NEUMATEX_PROXY_BODY_TOKEN"] == api["environment"]["NEUMATEX_PROXY_BODY_TOKEN"]
    assert len(api["environment"]["NEUMATEX_PROXY_BODY_TOKEN"]) >= 16
    uid = re.search(r"useradd [^\n]*--uid (\d+)", (ROOT / "deploy" / "Dockerfile").read_text())
    assert uid and proxy["user"].split(":")[0] == uid.group(1)
    assert f"install -d -o neumatex -m 0700 {body_dir}" in (ROOT / "deploy" / "Dockerfile").read_text()
    # clients reach the API only through the proxy; every name the template needs is set
    assert "ports" not in api and proxy["ports"]
    needed = set(re.findall(r"\$\{(NEUMATEX_[A-Z_]+)\}", (ROOT / template.split(":")[0]).read_text()))
    assert needed <= set(proxy["environment"]) and proxy["environment"]["NGINX_ENVSUBST_FILTER"] == "^NEUMATEX_"


# -- images ----------------------------------------------------------------------------------------------------
def dockerfile_stages(path: Path) -> dict[str, dict[str, Any]]:
    """{stage name: {"from": image, "runs": [RUN commands], "env": text of its ENV lines}} of a Dockerfile, with
    continuation lines joined and comments dropped."""
    logical: list[str] = []
    buf = ""
    for raw in path.read_text().splitlines():
        line = raw.strip()
        if not buf and (not line or line.startswith("#")):
            continue
        if line.startswith("#"):
            continue
        if line.endswith("\\"):
            buf += line[:-1].strip() + " "
            continue
        logical.append((buf + line).strip())
        buf = ""
    stages: dict[str, dict[str, Any]] = {}
    current: dict[str, Any] | None = None
    for line in logical:
        word, _, rest = line.partition(" ")
        word = word.upper()
        if word == "FROM":
            m = re.match(r"(\S+)(?:\s+AS\s+(\S+))?$", rest.strip(), re.IGNORECASE)
            assert m, line
            current = {"from": m.group(1), "runs": [], "env": ""}
            stages[m.group(2) or f"stage{len(stages)}"] = current
        elif current is not None and word == "RUN":
            current["runs"].append(" ".join(rest.split()))
        elif current is not None and word == "ENV":
            current["env"] += rest + "\n"
    return stages


def makefile_install_recipe() -> list[str]:
    """The commands of the Makefile's install recipe ($(STAMP), which `install` depends on), variables expanded
    with their defaults."""
    text = (ROOT / "Makefile").read_text()
    variables = dict(re.findall(r"^([A-Z][A-Z0-9_]*)\s*[:?]?=\s*(.*?)\s*$", text, re.MULTILINE))

    def expand(s: str) -> str:
        for _ in range(10):
            s = re.sub(r"\$\(([A-Z][A-Z0-9_]*)\)", lambda m: variables.get(m.group(1), m.group(0)), s)
        assert "$(" not in s, f"unexpanded Makefile variable in {s!r}"
        return s

    install = re.search(r"^install:\s*(.+)$", text, re.MULTILINE)
    assert install, "the Makefile has no install target"
    target = install.group(1).strip()
    lines = text.splitlines()
    start = next(i for i, ln in enumerate(lines) if re.match(re.escape(target) + r"\s*:", ln))
    recipe = []
    for ln in lines[start + 1:]:
        if not ln.startswith("\t"):
            break
        recipe.append(" ".join(expand(ln.strip().lstrip("@")).split()))
    assert recipe, "the install recipe is empty"
    return recipe


@needs_compose
def test_every_referenced_dockerfile_exists_with_its_flavour(main_config: dict[str, Any],
                                                             worker_config: dict[str, Any]) -> None:
    images: dict[str, Any] = {}
    for config in (main_config, worker_config):
        for name, s in app_services(config).items():
            build = s["build"]
            dockerfile = Path(build["context"]) / build.get("dockerfile", "Dockerfile")
            assert dockerfile.is_file(), f"{name}: {dockerfile} does not exist"
            assert Path(build["context"]).resolve() == ROOT, f"{name}: the build context must be the repository"
            flavour = build["args"]["FLAVOUR"]
            assert f"base-{flavour}" in dockerfile_stages(dockerfile), f"{name}: no stage base-{flavour}"
            # services sharing an image tag build it identically
            images.setdefault(s["image"], build)
            assert images[s["image"]] == build, f"{name}: image {s['image']} built two ways"
    assert main_config["services"]["worker-gpu"]["build"]["args"]["FLAVOUR"] == "gpu"
    assert all(s["build"]["args"]["FLAVOUR"] == "cpu" for n, s in app_services(main_config).items()
               if n != "worker-gpu")  # fmt: skip
    assert (ROOT / "deploy" / "healthcheck.py").is_file()


def test_dockerfile_installs_with_the_makefile_recipe() -> None:
    # "The images' build steps are the commands make uses": the final stage's first RUN commands are the
    # Makefile's install recipe, command for command, and nothing else in the Dockerfile installs Python packages.
    recipe = makefile_install_recipe()
    assert any("pip install" in c and "torch==" in c for c in recipe), recipe
    stages = dockerfile_stages(ROOT / "deploy" / "Dockerfile")
    app = stages["app"]
    assert app["runs"][:len(recipe)] == recipe, (
        f"deploy/Dockerfile installs with\n  {app['runs'][:len(recipe)]}\nbut `make install` runs\n  {recipe}")
    others = [c for name, st in stages.items() for i, c in enumerate(st["runs"])
              if "pip" in c and not (name == "app" and i < len(recipe))]  # fmt: skip
    assert not others, f"pip outside the Makefile's recipe: {others}"
    # CPU image: torch's CPU wheel; GPU image: a CUDA base image
    assert "download.pytorch.org/whl/cpu" in stages["base-cpu"]["env"]
    assert "download.pytorch.org" not in stages["base-gpu"]["env"]
    arg = re.search(r"^ARG CUDA_IMAGE=(\S+)", (ROOT / "deploy" / "Dockerfile").read_text(), re.MULTILINE)
    assert stages["base-gpu"]["from"] == "${CUDA_IMAGE}" and arg and arg.group(1).startswith("nvidia/cuda:")
    assert stages["app"]["from"] == "base-${FLAVOUR}"


# -- configuration ---------------------------------------------------------------------------------------------
def test_env_example_documents_every_substituted_variable() -> None:
    missing = substituted_vars() - env_example_keys()
    assert not missing, f".env.example does not document {sorted(missing)}"
    for key in env_example_keys() - WORKER_ONLY_VARS:
        assert not key.startswith("NEUMATEX_"), f"{key}: .env is also read by the service's settings"


@needs_compose
def test_compose_environment_names_are_service_settings(main_config: dict[str, Any],
                                                        worker_config: dict[str, Any]) -> None:
    from services.core.config import Settings

    fields = set(Settings.model_fields)
    for config in (main_config, worker_config):
        for name, s in app_services(config).items():
            for key in s["environment"]:
                if key in NON_SETTINGS_ENV:
                    continue
                assert key.startswith("NEUMATEX_"), f"{name}: {key} is not a NEUMATEX_ setting"
                assert key[len("NEUMATEX_"):].lower() in fields, \
                    f"{name}: {key} is not a field of services.core.config.Settings"


@needs_compose
def test_compose_environment_values_are_valid_settings(main_config: dict[str, Any],
                                                       monkeypatch: pytest.MonkeyPatch) -> None:
    from services.core.config import Settings

    for key in list(os.environ):
        if key.startswith("NEUMATEX_"):
            monkeypatch.delenv(key)
    for key, value in main_config["services"]["api"]["environment"].items():
        monkeypatch.setenv(key, "" if value is None else str(value))
    st = Settings(_env_file=None)  # type: ignore[call-arg]
    assert st.storage == "s3" and st.db_url.startswith("postgresql+psycopg://")
    assert st.redis_url.startswith("redis://")
