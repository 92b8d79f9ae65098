//! Builds the C++ side of the solver bridge against Debian's Ceres 2.1.
//!
//! Debian ships no `ceres.pc`, so Ceres and glog are linked by name; Eigen's
//! include path comes from `pkg-config eigen3` when available.
use std::process::Command;

fn eigen_include_dirs() -> Vec<String> {
    let from_pkg_config = Command::new("pkg-config")
        .args(["--cflags-only-I", "eigen3"])
        .output()
        .ok()
        .filter(|out| out.status.success())
        .map(|out| {
            String::from_utf8_lossy(&out.stdout)
                .split_whitespace()
                .filter_map(|flag| flag.strip_prefix("-I").map(str::to_owned))
                .collect::<Vec<_>>()
        })
        .unwrap_or_default();
    if from_pkg_config.is_empty() {
        println!("cargo:warning=pkg-config found no eigen3; trying /usr/include/eigen3");
        vec!["/usr/include/eigen3".to_owned()]
    } else {
        from_pkg_config
    }
}

fn main() {
    let sources = ["cpp/camera_bridge.cc", "cpp/bundle_adjustment.cc"];
    let mut build = cxx_build::bridges(["src/solver/ffi.rs"]);
    build
        .files(sources)
        .include("cpp")
        .std("c++17")
        .flag_if_supported("-Wno-unused-parameter")
        .flag_if_supported("-Wno-deprecated-declarations")
        .flag_if_supported("-Wno-ignored-attributes")
        .flag_if_supported("-Wno-class-memaccess")
        .opt_level(2);
    for dir in eigen_include_dirs() {
        build.include(dir);
    }
    build.compile("colmap_lidar_cpp");

    println!("cargo:rustc-link-lib=ceres");
    println!("cargo:rustc-link-lib=glog");
    println!("cargo:rustc-link-lib=gflags");
    for path in ["src/solver/ffi.rs", "cpp"] {
        println!("cargo:rerun-if-changed={path}");
    }
}
