#!/usr/bin/env bash
# Build ROS 2 interface packages (ament_cmake + rosidl) with the ROS wheels of a Python venv and
# install them into that venv, where they import with no environment set up.
#   interfaces/build.sh [--venv DIR] [--build-dir DIR] PACKAGE_DIR...
# DIR defaults to $VIRTUAL_ENV; packages are built in dependency order whatever order is given.
# A package the venv already has from elsewhere is skipped: see skip_reason below.
set -euo pipefail

venv="${VIRTUAL_ENV:-}"
build_root="build/interfaces"
pkgs=()
while (($#)); do
  case "$1" in
    --venv) venv="$2"; shift 2 ;;
    --build-dir) build_root="$2"; shift 2 ;;
    -h|--help) sed -n '2,6p' "$0"; exit 0 ;;
    *) pkgs+=("$1"); shift ;;
  esac
done
[[ -n "$venv" ]] || { echo "build.sh: no venv (activate one or pass --venv DIR)" >&2; exit 2; }
((${#pkgs[@]})) || { echo "build.sh: no package directory given" >&2; exit 2; }
# the real path: it ends up in installed CMake and ament index files
venv="$(cd "$venv" && pwd -P)"
py="$venv/bin/python"
[[ -x "$py" ]] || { echo "build.sh: $py not found" >&2; exit 2; }
mkdir -p "$build_root"
build_root="$(cd "$build_root" && pwd -P)"

# ament finds its CMake modules and the message packages through these
export AMENT_PREFIX_PATH="$venv${AMENT_PREFIX_PATH:+:$AMENT_PREFIX_PATH}"
export CMAKE_PREFIX_PATH="$venv${CMAKE_PREFIX_PATH:+:$CMAKE_PREFIX_PATH}"
export PATH="$venv/bin:$PATH"

# Why a package is not built (empty: build it). Hook for packages that exist elsewhere too: a
# control_msgs the venv already imports and that this script did not install (for example the
# wheel of ros2_control's own control_msgs) is used as it is, never overwritten.
skip_reason() {
  local name="$1"
  case "$name" in
    control_msgs)
      if [[ ! -e "$venv/share/$name/dyn_node_built" ]] \
          && "$py" -c "import $name.msg" >/dev/null 2>&1; then
        echo "the venv already has a $name that is not built from this repository"
      fi ;;
  esac
}

# package directories in dependency order (a package after those of the others it depends on)
mapfile -t ordered < <("$py" - "${pkgs[@]}" <<'PY'
import sys
import xml.etree.ElementTree as ET
from pathlib import Path

dirs = {}
for d in sys.argv[1:]:
    root = ET.parse(Path(d) / "package.xml").getroot()
    deps = {e.text.strip() for e in root if e.tag.endswith("depend") and e.text}
    dirs[root.findtext("name").strip()] = (d, deps)
done: list[str] = []
def visit(name: str, path: tuple[str, ...]) -> None:
    if name in done:
        return
    if name in path:
        sys.exit(f"build.sh: dependency cycle {' -> '.join(path + (name,))}")
    for dep in sorted(dirs[name][1] & dirs.keys()):
        visit(dep, path + (name,))
    done.append(name)
for name in sorted(dirs):
    visit(name, ())
print("\n".join(f"{n}\t{dirs[n][0]}" for n in done))
PY
)

for entry in "${ordered[@]}"; do
  name="${entry%%$'\t'*}"
  src="$(cd "${entry#*$'\t'}" && pwd -P)"
  reason="$(skip_reason "$name")"
  if [[ -n "$reason" ]]; then
    echo "build.sh: skipping $name: $reason"
    continue
  fi
  echo "build.sh: building $name into $venv"
  cmake -S "$src" -B "$build_root/$name" -DCMAKE_INSTALL_PREFIX="$venv" \
    -DPython3_EXECUTABLE="$py" -DBUILD_TESTING=OFF -DCMAKE_BUILD_TYPE=Release \
    -Wno-dev --log-level=WARNING >/dev/null
  cmake --build "$build_root/$name" -j "$(nproc)"
  cmake --install "$build_root/$name" >/dev/null
  # marks the installed package as ours (skip_reason's test)
  echo "$src" > "$venv/share/$name/dyn_node_built"
done
