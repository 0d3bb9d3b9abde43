#!/usr/bin/env bash
# Build vision_msgs Python bindings from gd_completion/msg/vision_msgs/*.msg into <build_dir>/install
# (default: build/interfaces in the repository).
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
msg_dir="$repo/gd_completion/msg/vision_msgs"
install="$build_dir/install"
stamp="$install/.gd_interfaces_stamp"

[ -x "$python" ] || { echo "build_interfaces: no python at $python (run scripts/install.sh)" >&2; exit 2; }
[ -d "$msg_dir" ] || { echo "build_interfaces: no message folder $msg_dir" >&2; exit 2; }

want=$( (cd "$msg_dir" && cat ./*.msg; cat "$self"; echo "$venv"; \
         ls "$venv"/lib/python3*/site-packages | grep -E '^ros_.*dist-info$') | sha256sum | cut -d' ' -f1)
if [ -f "$stamp" ] && [ "$(cat "$stamp")" = "$want" ]; then
  exit 0
fi

# One build at a time per build dir (parallel test processes).
exec 9>"$build_dir/.lock"
flock 9
if [ -f "$stamp" ] && [ "$(cat "$stamp")" = "$want" ]; then
  exit 0
fi

# The wheels' own environment: venv libraries, venv as the only ament/cmake prefix.
export _ROS_WHEELS_BOOTSTRAP_COMPLETE=1
site=$("$python" -c 'import sysconfig; print(sysconfig.get_paths()["purelib"])')
py_include=$("$python" -c 'import sysconfig; print(sysconfig.get_paths()["include"])')
np_include=$("$python" -c 'import numpy; print(numpy.get_include())')
export LD_LIBRARY_PATH="$venv/lib:$(ls -d "$site"/ros_*.libs 2>/dev/null | paste -sd:)${LD_LIBRARY_PATH:+:$LD_LIBRARY_PATH}"
export AMENT_PREFIX_PATH="$venv"
export CMAKE_PREFIX_PATH="$venv"
export PATH="$venv/bin:$PATH"
export PYTHONPATH="$site${PYTHONPATH:+:$PYTHONPATH}"
export RMW_IMPLEMENTATION=rmw_fastrtps_cpp

src="$build_dir/src/vision_msgs"
rm -rf "$src/msg"
mkdir -p "$src/msg"
cp "$msg_dir"/*.msg "$src/msg/"
msgs=$(cd "$src" && ls msg/*.msg | sed 's/^/  "/; s/$/"/')

cat > "$src/package.xml" <<'EOF'
<?xml version="1.0"?>
<?xml-model href="http://download.ros.org/schema/package_format3.xsd" schematypens="http://www.w3.org/2001/XMLSchema"?>
<package format="3">
  <name>vision_msgs</name>
  <version>4.1.1</version>
  <description>Subset of vision_msgs (ROS 2 Jazzy, 4.x) built locally for gd_completion.</description>
  <maintainer email="dev@gd-completion.invalid">gd_completion developers</maintainer>
  <license>Apache License 2.0</license>
  <buildtool_depend>ament_cmake</buildtool_depend>
  <buildtool_depend>rosidl_default_generators</buildtool_depend>
  <depend>std_msgs</depend>
  <depend>geometry_msgs</depend>
  <exec_depend>rosidl_default_runtime</exec_depend>
  <member_of_group>rosidl_interface_packages</member_of_group>
  <export>
    <build_type>ament_cmake</build_type>
  </export>
</package>
EOF

cat > "$src/CMakeLists.txt" <<EOF
cmake_minimum_required(VERSION 3.16)
project(vision_msgs)
find_package(ament_cmake REQUIRED)
find_package(rosidl_default_generators REQUIRED)
find_package(std_msgs REQUIRED)
find_package(geometry_msgs REQUIRED)

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
  DEPENDENCIES std_msgs geometry_msgs
)
ament_export_dependencies(rosidl_default_runtime)
ament_package()
EOF

generator=()
command -v ninja >/dev/null && generator=(-G Ninja)
obj="$build_dir/cmake"
if [ -f "$obj/CMakeCache.txt" ] && ! grep -q "CMAKE_INSTALL_PREFIX:PATH=$install\$" "$obj/CMakeCache.txt"; then
  rm -rf "$obj"
fi
if [ -f "$obj/CMakeCache.txt" ] && [ ${#generator[@]} -gt 0 ] && ! grep -q "CMAKE_GENERATOR:INTERNAL=Ninja" "$obj/CMakeCache.txt"; then
  rm -rf "$obj"
fi
log="$build_dir/build.log"
: > "$log"
run() { "$@" >>"$log" 2>&1 || { echo "build_interfaces: failed: $* (log: $log)" >&2; tail -40 "$log" >&2; exit 1; }; }
run cmake -S "$src" -B "$obj" "${generator[@]}" \
  -DCMAKE_BUILD_TYPE=Release -DBUILD_TESTING=OFF \
  -DCMAKE_INSTALL_PREFIX="$install" \
  -DCMAKE_PREFIX_PATH="$venv" \
  -DPython3_EXECUTABLE="$python" -DPython3_FIND_STRATEGY=LOCATION -DPython3_FIND_VIRTUALENV=ONLY \
  -DPython3_INCLUDE_DIR="$py_include" -DPython3_NumPy_INCLUDE_DIR="$np_include" \
  -DPYTHON_EXECUTABLE="$python" \
  -DCMAKE_INSTALL_RPATH="\$ORIGIN;\$ORIGIN/../../..;$install/lib;$venv/lib" \
  -DCMAKE_BUILD_WITH_INSTALL_RPATH=OFF
run cmake --build "$obj" -j "${GD_BUILD_JOBS:-2}"
run cmake --install "$obj"
echo "$want" > "$stamp"
echo "build_interfaces: vision_msgs installed in $install"
