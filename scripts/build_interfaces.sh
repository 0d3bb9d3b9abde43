#!/usr/bin/env bash
# Build the Python bindings of the message packages that have no PyPI wheel from gd_completion/msg/<package>/*.msg
# into <build_dir>/install (default: build/interfaces in the repository): vision_msgs, tf2_msgs (TFMessage) and
# autoware_perception_msgs (DetectedObjects, TrackedObjects). One CMake package per message package, built in the
# order of PACKAGES (a package may depend on an earlier one) and installed into the same prefix, so one PYTHONPATH /
# LD_LIBRARY_PATH / AMENT_PREFIX_PATH entry serves all of them.
#
# Uses only the virtualenv ($GD_VENV, else <repo>/.venv, else $VIRTUAL_ENV): the ROS 2 Jazzy PyPI wheels
# put their CMake configs under <venv>/share and their libraries under <venv>/lib, so the venv is the ament
# prefix. The wheels' exported *__rosidl_generator_pyExport.cmake files hard-code /opt/python/cp311-cp311
# include dirs; the generated CMakeLists.txt rewrites those paths on the imported targets after find_package
# (the venv is never modified, so this is idempotent by construction).
# Idempotent: exits at once when <build_dir>/install matches the current .msg files, this script and the venv.
set -euo pipefail

self=$(cd "$(dirname "${BASH_SOURCE[0]}")" && pwd)/$(basename "${BASH_SOURCE[0]}")
repo=$(cd "$(dirname "$self")/.." && pwd)
build_dir=${1:-"$repo/build/interfaces"}
mkdir -p "$build_dir"
build_dir=$(cd "$build_dir" && pwd)
if [ -n "${GD_VENV:-}" ]; then venv=$GD_VENV
elif [ -x "$repo/.venv/bin/python" ] || [ -z "${VIRTUAL_ENV:-}" ]; then venv="$repo/.venv"
else venv=$VIRTUAL_ENV
fi
python="$venv/bin/python"
msg_root="$repo/gd_completion/msg"
install="$build_dir/install"
stamp="$install/.gd_interfaces_stamp"

# Build order; each package's version, licence and dependencies (the wheels' packages or earlier entries).
PACKAGES=(vision_msgs tf2_msgs autoware_perception_msgs)
package_info() {  # <package> -> sets version, license, deps
  case $1 in
    vision_msgs) version=4.1.1 license="Apache License 2.0" deps="std_msgs geometry_msgs" ;;
    tf2_msgs) version=0.36.4 license="BSD" deps="builtin_interfaces geometry_msgs" ;;
    autoware_perception_msgs)
      version=1.12.0 license="Apache License 2.0"
      deps="builtin_interfaces std_msgs geometry_msgs unique_identifier_msgs" ;;
    *) echo "build_interfaces: unknown package $1" >&2; exit 2 ;;
  esac
}

[ -x "$python" ] || { echo "build_interfaces: no python at $python (run scripts/install.sh)" >&2; exit 2; }
for pkg in "${PACKAGES[@]}"; do
  compgen -G "$msg_root/$pkg/*.msg" >/dev/null || { echo "build_interfaces: no .msg files in $msg_root/$pkg" >&2; exit 2; }
done

msg_texts() {  # every package's .msg files, each under its name
  local pkg f
  for pkg in "${PACKAGES[@]}"; do
    for f in "$msg_root/$pkg"/*.msg; do echo "== $pkg/${f##*/}"; cat "$f"; done
  done
}
want=$( (msg_texts; cat "$self"; echo "$venv"; ls "$venv"/lib/python3*/site-packages | grep -E '^ros_.*dist-info$') \
       | sha256sum | cut -d' ' -f1)
if [ -f "$stamp" ] && [ "$(cat "$stamp")" = "$want" ]; then
  exit 0
fi

# One build at a time per build dir (parallel test processes).
exec 9>"$build_dir/.lock"
flock 9
if [ -f "$stamp" ] && [ "$(cat "$stamp")" = "$want" ]; then
  exit 0
fi

# The wheels' own environment: venv libraries, venv (then the packages installed so far) as the ament/cmake prefix.
export _ROS_WHEELS_BOOTSTRAP_COMPLETE=1
site=$("$python" -c 'import sysconfig; print(sysconfig.get_paths()["purelib"])')
py_include=$("$python" -c 'import sysconfig; print(sysconfig.get_paths()["include"])')
np_include=$("$python" -c 'import numpy; print(numpy.get_include())')
export LD_LIBRARY_PATH="$install/lib:$venv/lib:$(ls -d "$site"/ros_*.libs 2>/dev/null | paste -sd:)${LD_LIBRARY_PATH:+:$LD_LIBRARY_PATH}"
export AMENT_PREFIX_PATH="$install:$venv"
export CMAKE_PREFIX_PATH="$install;$venv"
export PATH="$venv/bin:$PATH"
export PYTHONPATH="$site${PYTHONPATH:+:$PYTHONPATH}"
export RMW_IMPLEMENTATION=rmw_fastrtps_cpp

generator=()
command -v ninja >/dev/null && generator=(-G Ninja)
log="$build_dir/build.log"
: > "$log"
run() { "$@" >>"$log" 2>&1 || { echo "build_interfaces: failed: $* (log: $log)" >&2; tail -40 "$log" >&2; exit 1; }; }
# Before several packages, <build_dir>/cmake was vision_msgs' own build folder.
[ -f "$build_dir/cmake/CMakeCache.txt" ] && rm -rf "$build_dir/cmake"

write_package() {  # <package> <src>: package.xml and CMakeLists.txt of one message package
  local pkg=$1 src=$2 dep msgs depends="" finds="" version license deps
  package_info "$pkg"
  msgs=$(cd "$src" && ls msg/*.msg | sed 's/^/  "/; s/$/"/')
  for dep in $deps; do
    depends+="  <depend>$dep</depend>"$'\n'
    finds+="find_package($dep REQUIRED)"$'\n'
  done
  cat > "$src/package.xml" <<EOF
<?xml version="1.0"?>
<?xml-model href="http://download.ros.org/schema/package_format3.xsd" schematypens="http://www.w3.org/2001/XMLSchema"?>
<package format="3">
  <name>$pkg</name>
  <version>$version</version>
  <description>Subset of $pkg (ROS 2 Jazzy) built locally for gd_completion.</description>
  <maintainer email="dev@gd-completion.invalid">gd_completion developers</maintainer>
  <license>$license</license>
  <buildtool_depend>ament_cmake</buildtool_depend>
  <buildtool_depend>rosidl_default_generators</buildtool_depend>
$depends  <exec_depend>rosidl_default_runtime</exec_depend>
  <member_of_group>rosidl_interface_packages</member_of_group>
  <export>
    <build_type>ament_cmake</build_type>
  </export>
</package>
EOF
  cat > "$src/CMakeLists.txt" <<EOF
cmake_minimum_required(VERSION 3.16)
project($pkg)
find_package(ament_cmake REQUIRED)
find_package(rosidl_default_generators REQUIRED)
$finds
# The PyPI wheels export /opt/python/cp311-cp311 include dirs (the manylinux build Python): point them at this venv.
get_property(_imported DIRECTORY PROPERTY IMPORTED_TARGETS)
foreach(_t IN LISTS _imported)
  get_target_property(_inc \${_t} INTERFACE_INCLUDE_DIRECTORIES)
  if(_inc AND _inc MATCHES "/opt/python/")
    string(REPLACE "/opt/python/cp311-cp311/include/python3.11" "$py_include" _inc "\${_inc}")
    string(REPLACE "/opt/python/cp311-cp311/lib/python3.11/site-packages/numpy/_core/include" "$np_include" _inc "\${_inc}")
    set_target_properties(\${_t} PROPERTIES INTERFACE_INCLUDE_DIRECTORIES "\${_inc}")
  endif()
endforeach()

rosidl_generate_interfaces(\${PROJECT_NAME}
$msgs
  DEPENDENCIES $deps
)
ament_export_dependencies(rosidl_default_runtime)
ament_package()
EOF
}

for pkg in "${PACKAGES[@]}"; do
  src="$build_dir/src/$pkg"
  rm -rf "$src/msg"
  mkdir -p "$src/msg"
  cp "$msg_root/$pkg"/*.msg "$src/msg/"
  write_package "$pkg" "$src"
  obj="$build_dir/cmake/$pkg"
  if [ -f "$obj/CMakeCache.txt" ] && ! grep -q "CMAKE_INSTALL_PREFIX:PATH=$install\$" "$obj/CMakeCache.txt"; then
    rm -rf "$obj"
  fi
  if [ -f "$obj/CMakeCache.txt" ] && [ ${#generator[@]} -gt 0 ] && ! grep -q "CMAKE_GENERATOR:INTERNAL=Ninja" "$obj/CMakeCache.txt"; then
    rm -rf "$obj"
  fi
  echo "=== $pkg" >> "$log"
  run cmake -S "$src" -B "$obj" "${generator[@]}" \
    -DCMAKE_BUILD_TYPE=Release -DBUILD_TESTING=OFF \
    -DCMAKE_INSTALL_PREFIX="$install" \
    -DCMAKE_PREFIX_PATH="$install;$venv" \
    -DPython3_EXECUTABLE="$python" -DPython3_FIND_STRATEGY=LOCATION -DPython3_FIND_VIRTUALENV=ONLY \
    -DPython3_INCLUDE_DIR="$py_include" -DPython3_NumPy_INCLUDE_DIR="$np_include" \
    -DPYTHON_EXECUTABLE="$python" \
    -DCMAKE_INSTALL_RPATH="\$ORIGIN;\$ORIGIN/../../..;$install/lib;$venv/lib" \
    -DCMAKE_BUILD_WITH_INSTALL_RPATH=OFF
  run cmake --build "$obj" -j "${GD_BUILD_JOBS:-2}"
  run cmake --install "$obj"
done
echo "$want" > "$stamp"
echo "build_interfaces: ${PACKAGES[*]} installed in $install"
