#!/usr/bin/env bash
# Generate + compile the ROS 2 Jazzy message package tf2_msgs (TFMessage only)
# against a pip-wheel ROS install (ros-jazzy-rclpy / ros-jazzy-common-interfaces)
# without ament_cmake / colcon: the rosidl generators are run directly from
# Python with hand-written generator-argument JSON files, and the generated
# sources are compiled with plain gcc/g++.
#
# usage: build_tf2_msgs.sh /path/to/venv/bin/python /path/to/output_prefix
set -euo pipefail

PY=${1:?usage: $0 VENV_PYTHON OUTPUT_PREFIX}
PREFIX=${2:?usage: $0 VENV_PYTHON OUTPUT_PREFIX}
PKG=tf2_msgs
PKG_UPPER=TF2_MSGS
NICE=${NICE:-nice -n 10}
T0=$(date +%s%N)

# do NOT resolve symlinks (venv python -> base python)
case "$PY" in /*) ;; *) PY=$(command -v "$PY" || echo "$PWD/$PY");; esac
mkdir -p "$PREFIX"; PREFIX=$(cd "$PREFIX" && pwd)
# venv prefix (sys.prefix), python version, include dirs
read -r VENV PYVER PYINC NPINC EXT_SUFFIX < <(_ROS_WHEELS_BOOTSTRAP_COMPLETE=1 "$PY" -c '
import sys, sysconfig, numpy
print(sys.prefix, "%d.%d" % sys.version_info[:2], sysconfig.get_paths()["include"],
      numpy.get_include(), sysconfig.get_config_var("EXT_SUFFIX"))')
VLIB=$VENV/lib
VSHARE=$VENV/share
VINC=$VENV/include
for d in geometry_msgs std_msgs builtin_interfaces; do
  [ -d "$VSHARE/$d/msg" ] || { echo "missing $VSHARE/$d/msg (dependency interfaces)" >&2; exit 1; }
done

BUILD=$PREFIX/build
SRC=$BUILD/src/$PKG
GEN=$BUILD/gen
rm -rf "$BUILD"; mkdir -p "$SRC/msg" "$GEN"
SITE=$PREFIX/lib/python$PYVER/site-packages
mkdir -p "$PREFIX/lib" "$SITE" "$PREFIX/include/$PKG" "$PREFIX/share/$PKG/msg" \
         "$PREFIX/share/ament_index/resource_index/packages" \
         "$PREFIX/share/ament_index/resource_index/rosidl_interfaces" \
         "$PREFIX/share/ament_index/resource_index/package_run_dependencies"

# ---------------------------------------------------------------- interface
echo 'geometry_msgs/TransformStamped[] transforms' > "$SRC/msg/TFMessage.msg"
cat > "$SRC/package.xml" <<'EOF'
<?xml version="1.0"?>
<package format="3">
  <name>tf2_msgs</name>
  <version>0.36.0</version>
  <description>tf2_msgs (TFMessage only), generated outside ament</description>
  <maintainer email="none@example.com">none</maintainer>
  <license>BSD-3-Clause</license>
  <buildtool_depend>ament_cmake</buildtool_depend>
  <depend>geometry_msgs</depend>
  <member_of_group>rosidl_interface_packages</member_of_group>
  <export><build_type>ament_cmake</build_type></export>
</package>
EOF

export _ROS_WHEELS_BOOTSTRAP_COMPLETE=1   # generators need no re-exec
export PYTHONDONTWRITEBYTECODE=1

# ---------------------------------------------------------------- generation
$NICE "$PY" - "$SRC" "$GEN" "$VSHARE" "$VENV" <<'PYEOF'
import json, os, subprocess, sys, pathlib
src, gen, vshare, venv = sys.argv[1:5]
pkg = 'tf2_msgs'
from rosidl_adapter.msg import convert_msg_to_idl
convert_msg_to_idl(pathlib.Path(src), pkg, pathlib.Path('msg/TFMessage.msg'),
                   pathlib.Path(src) / 'msg')
idl_tuples = [f'{src}:msg/TFMessage.idl']
dep_pkgs = ['geometry_msgs', 'std_msgs', 'builtin_interfaces']
deps = []
for d in dep_pkgs:
    for f in sorted(os.listdir(os.path.join(vshare, d, 'msg'))):
        if f.endswith('.idl'):
            deps.append(f'{d}:{os.path.join(vshare, d, "msg", f)}')

def run(tool, args, extra=()):
    fn = os.path.join(gen, f'{tool}__arguments.json')
    with open(fn, 'w') as fh:
        json.dump(args, fh, indent=2)
    exe = os.path.join(venv, 'lib', tool, tool)
    subprocess.check_call([sys.executable, exe, '--generator-arguments-file', fn, *extra])

def tdir(tool):
    return os.path.join(vshare, tool, 'resource')

# 1. type description JSON + RIHS01 type hash (needs deps' share/<pkg>/msg/*.json)
run('rosidl_generator_type_description', {
    'package_name': pkg, 'idl_tuples': idl_tuples,
    'output_dir': f'{gen}/rosidl_generator_type_description/{pkg}',
    'include_paths': [f'{d}:{os.path.join(vshare, d)}' for d in dep_pkgs]})
td_tuples = [f'msg/TFMessage.idl:{gen}/rosidl_generator_type_description/{pkg}/msg/TFMessage.json']
common = {'package_name': pkg, 'idl_tuples': idl_tuples,
          'ros_interface_dependencies': deps, 'target_dependencies': []}
# 2. C structs / functions / description
run('rosidl_generator_c', {**common, 'output_dir': f'{gen}/rosidl_generator_c/{pkg}',
    'template_dir': tdir('rosidl_generator_c'), 'type_description_tuples': td_tuples,
    'ros_interface_files': [f'{src}/msg/TFMessage.msg']})
# 3. typesupports
run('rosidl_typesupport_introspection_c', {**common,
    'output_dir': f'{gen}/rosidl_typesupport_introspection_c/{pkg}',
    'template_dir': tdir('rosidl_typesupport_introspection_c')})
run('rosidl_typesupport_fastrtps_c', {**common,
    'output_dir': f'{gen}/rosidl_typesupport_fastrtps_c/{pkg}',
    'template_dir': tdir('rosidl_typesupport_fastrtps_c')})
run('rosidl_typesupport_c', {**common, 'output_dir': f'{gen}/rosidl_typesupport_c/{pkg}',
    'template_dir': tdir('rosidl_typesupport_c')},
    ['--typesupports', 'rosidl_typesupport_fastrtps_c', 'rosidl_typesupport_introspection_c'])
# 4. Python
run('rosidl_generator_py', {**common, 'output_dir': f'{gen}/rosidl_generator_py/{pkg}',
    'template_dir': tdir('rosidl_generator_py')},
    ['--typesupport-impls',
     'rosidl_typesupport_c;rosidl_typesupport_fastrtps_c;rosidl_typesupport_introspection_c'])
open(f'{gen}/rosidl_generator_py/{pkg}/__init__.py', 'a').close()
PYEOF

# visibility headers (cmake configure_file equivalents)
vis() { sed -e "s/@PROJECT_NAME@/$PKG/g" -e "s/@PROJECT_NAME_UPPER@/$PKG_UPPER/g" \
              "$VSHARE/$1/resource/$1__visibility_control.h.in" > "$GEN/$1/$PKG/msg/$1__visibility_control.h"; }
vis rosidl_generator_c
vis rosidl_typesupport_introspection_c
vis rosidl_typesupport_fastrtps_c

T1=$(date +%s%N)
# ---------------------------------------------------------------- compile
INC=(-I"$GEN/rosidl_generator_c" -I"$GEN/rosidl_typesupport_introspection_c"
     -I"$GEN/rosidl_typesupport_fastrtps_c" -I"$GEN/rosidl_generator_py" -I"$VINC")
for d in "$VINC"/*/; do case "$d" in */python*) ;; *) INC+=(-I"${d%/}");; esac; done
LDF=(-shared -fPIC -L"$PREFIX/lib" -L"$VLIB" -Wl,--no-undefined
     -Wl,-rpath,"$PREFIX/lib" -Wl,-rpath,"$VLIB")
CF=(-O2 -fPIC -fvisibility=hidden -w)
dl() { for p in geometry_msgs std_msgs builtin_interfaces; do echo "-l${p}__$1"; done; }
cc()  { echo "  CC  $(basename $1)"; shift; $NICE gcc -std=gnu11 "${CF[@]}" "${INC[@]}" "$@"; }
cxx() { echo "  CXX $(basename $1)"; shift; $NICE g++ -std=c++17 "${CF[@]}" "${INC[@]}" "$@"; }
L=$PREFIX/lib
C=$GEN/rosidl_generator_c/$PKG/msg/detail
cc "$L/lib${PKG}__rosidl_generator_c.so" -DROSIDL_GENERATOR_C_BUILDING_DLL_$PKG \
   $C/tf_message__description.c $C/tf_message__functions.c $C/tf_message__type_support.c \
   "${LDF[@]}" $(dl rosidl_generator_c) -lrosidl_runtime_c -lrcutils -o "$L/lib${PKG}__rosidl_generator_c.so"
I=$GEN/rosidl_typesupport_introspection_c/$PKG/msg/detail
cc "$L/lib${PKG}__rosidl_typesupport_introspection_c.so" -DROSIDL_TYPESUPPORT_INTROSPECTION_C_BUILDING_DLL_$PKG \
   $I/tf_message__type_support.c "${LDF[@]}" -l${PKG}__rosidl_generator_c \
   $(dl rosidl_typesupport_introspection_c) $(dl rosidl_generator_c) \
   -lrosidl_typesupport_introspection_c -lrosidl_runtime_c -lrcutils \
   -o "$L/lib${PKG}__rosidl_typesupport_introspection_c.so"
F=$GEN/rosidl_typesupport_fastrtps_c/$PKG/msg/detail
cxx "$L/lib${PKG}__rosidl_typesupport_fastrtps_c.so" -DROSIDL_TYPESUPPORT_FASTRTPS_C_BUILDING_DLL_$PKG \
   $F/tf_message__type_support_c.cpp "${LDF[@]}" -l${PKG}__rosidl_generator_c \
   $(dl rosidl_typesupport_fastrtps_c) $(dl rosidl_generator_c) \
   -lrosidl_typesupport_fastrtps_c -lrosidl_typesupport_fastrtps_cpp -lrosidl_dynamic_typesupport \
   -lrmw -lfastcdr -lrosidl_runtime_c -lrcutils -o "$L/lib${PKG}__rosidl_typesupport_fastrtps_c.so"
S=$GEN/rosidl_typesupport_c/$PKG/msg
cxx "$L/lib${PKG}__rosidl_typesupport_c.so" -DROSIDL_GENERATOR_C_BUILDING_DLL_$PKG \
   $S/tf_message__type_support.cpp "${LDF[@]}" -l${PKG}__rosidl_generator_c \
   $(dl rosidl_typesupport_c) $(dl rosidl_generator_c) \
   -lrosidl_typesupport_c -lrosidl_runtime_c -lrcutils -ldl -o "$L/lib${PKG}__rosidl_typesupport_c.so"
P=$GEN/rosidl_generator_py/$PKG
cc "$L/lib${PKG}__rosidl_generator_py.so" -I"$PYINC" -I"$NPINC" $P/msg/_tf_message_s.c \
   "${LDF[@]/--no-undefined/--allow-shlib-undefined}" -l${PKG}__rosidl_typesupport_c -l${PKG}__rosidl_generator_c \
   $(dl rosidl_generator_py) $(dl rosidl_typesupport_c) $(dl rosidl_generator_c) \
   -lrosidl_runtime_c -lrcutils -o "$L/lib${PKG}__rosidl_generator_py.so"
mkdir -p "$SITE/$PKG"
cp -r "$P"/__init__.py "$P"/msg "$SITE/$PKG/"
rm -f "$SITE/$PKG"/msg/*.c
for ts in rosidl_typesupport_c rosidl_typesupport_fastrtps_c rosidl_typesupport_introspection_c; do
  cc "${PKG}_s__$ts" -I"$PYINC" -I"$NPINC" "$P/_${PKG}_s.ep.$ts.c" \
     "${LDF[@]/--no-undefined/--allow-shlib-undefined}" -l${PKG}__rosidl_generator_py -l${PKG}__$ts \
     -l${PKG}__rosidl_typesupport_c -l${PKG}__rosidl_generator_c \
     -lrosidl_runtime_c -lrosidl_typesupport_c -lrmw -lrcutils -o "$SITE/$PKG/${PKG}_s__$ts$EXT_SUFFIX"
done

# ---------------------------------------------------------------- install data
for g in rosidl_generator_c rosidl_typesupport_introspection_c rosidl_typesupport_fastrtps_c; do
  (cd "$GEN/$g" && find . -name '*.h' -exec cp --parents {} "$PREFIX/include/$PKG/" \;)
done
cp "$SRC/msg/TFMessage.msg" "$SRC/msg/TFMessage.idl" \
   "$GEN/rosidl_generator_type_description/$PKG/msg/TFMessage.json" "$PREFIX/share/$PKG/msg/"
cp "$SRC/package.xml" "$PREFIX/share/$PKG/"
RI=$PREFIX/share/ament_index/resource_index
: > "$RI/packages/$PKG"
printf 'msg/TFMessage.idl\nmsg/TFMessage.msg' > "$RI/rosidl_interfaces/$PKG"
printf 'builtin_interfaces;geometry_msgs;rosidl_default_runtime;std_msgs' > "$RI/package_run_dependencies/$PKG"
[ "${KEEP_BUILD:-0}" = 1 ] || rm -rf "$BUILD"

T2=$(date +%s%N)
awk -v a="$T0" -v b="$T1" -v c="$T2" -v size="$(du -sh "$PREFIX" | cut -f1)" 'BEGIN {
  printf "# generate %.1fs, compile %.1fs, total %.1fs; prefix size %s\n", (b-a)/1e9, (c-b)/1e9, (c-a)/1e9, size }'
cat <<EOF
export PYTHONPATH=$SITE\${PYTHONPATH:+:\$PYTHONPATH}
export LD_LIBRARY_PATH=$PREFIX/lib:$VLIB\${LD_LIBRARY_PATH:+:\$LD_LIBRARY_PATH}
export AMENT_PREFIX_PATH=$PREFIX:$VENV\${AMENT_PREFIX_PATH:+:\$AMENT_PREFIX_PATH}
EOF
