//! Compiles every `kernels/*.wgsl` to SPIR-V with naga (pure Rust, no system tool) and writes
//! the kernel table `$OUT_DIR/kernels.rs` (`duv_map::vulkan::kernels`, data for `duv_gpu::GpuContext::new`): one entry per compute entry
//! point with its workgroup size, its bindings (from naga's reflection: binding number,
//! read-only or read-write storage, type) and the size of its immediate (push-constant)
//! block, and whether it needs float atomics (`atomic<f32>`), so no binding list is written by
//! hand.
//!
//! SPIR-V options: workgroup memory is NOT zero-initialised (naga's default polyfill made
//! kernels 4-8x slower on lavapipe); every kernel initialises the shared memory it reads.

use std::fmt::Write as _;
use std::path::{Path, PathBuf};

use naga::back::spv;
use naga::valid::{Capabilities, ValidationFlags, Validator};

fn main() {
    let kernels_dir = Path::new(env!("CARGO_MANIFEST_DIR")).join("../../kernels");
    println!("cargo:rerun-if-changed={}", kernels_dir.display());
    let out_dir = PathBuf::from(std::env::var("OUT_DIR").expect("OUT_DIR"));
    let mut files: Vec<PathBuf> = std::fs::read_dir(&kernels_dir)
        .expect("kernels/ folder")
        .map(|e| e.expect("kernels/ entry").path())
        .filter(|p| p.extension().is_some_and(|e| e == "wgsl"))
        .collect();
    files.sort();

    let mut table = String::new();
    let mut variants = String::new();
    let mut all = String::new();
    let mut count = 0usize;
    for path in &files {
        println!("cargo:rerun-if-changed={}", path.display());
        let stem = path.file_stem().unwrap().to_str().unwrap().to_owned();
        let source = with_includes(&std::fs::read_to_string(path).unwrap_or_else(|e| panic!("{}: {e}", path.display())), &kernels_dir.join("shared"));
        let module = naga::front::wgsl::parse_str(&source)
            .unwrap_or_else(|e| panic!("\n{}", e.emit_to_string_with_path(&source, &path.display().to_string())));
        let info = Validator::new(ValidationFlags::all(), Capabilities::IMMEDIATES | Capabilities::SUBGROUP | Capabilities::SHADER_FLOAT32_ATOMIC)
            .subgroup_stages(naga::valid::ShaderStages::COMPUTE)
            .subgroup_operations(naga::valid::SubgroupOperationSet::all())
            .validate(&module)
            .unwrap_or_else(|e| panic!("\n{}", e.emit_to_string_with_path(&source, &path.display().to_string())));
        for (ep_index, ep) in module.entry_points.iter().enumerate() {
            if ep.stage != naga::ShaderStage::Compute {
                continue;
            }
            let options = spv::Options {
                lang_version: (1, 3),
                flags: spv::WriterFlags::empty(),
                zero_initialize_workgroup_memory: spv::ZeroInitializeWorkgroupMemoryMode::None,
                force_loop_bounding: false,
                ..Default::default()
            };
            let pipeline = spv::PipelineOptions { shader_stage: naga::ShaderStage::Compute, entry_point: ep.name.clone() };
            let words = spv::write_vec(&module, &info, &options, Some(&pipeline))
                .unwrap_or_else(|e| panic!("{}: entry point {}: SPIR-V: {e}", path.display(), ep.name));
            let spv_name = format!("{stem}.{}.spv", ep.name);
            let bytes: Vec<u8> = words.iter().flat_map(|w| w.to_le_bytes()).collect();
            std::fs::write(out_dir.join(&spv_name), bytes).expect("write SPIR-V");

            // Reflection: the globals this entry point uses.
            let ep_info = info.get_entry_point(ep_index);
            let mut bindings = Vec::new();
            let mut immediate_bytes = 0u32;
            let mut float_atomics = false;
            for (handle, var) in module.global_variables.iter() {
                if ep_info[handle].is_empty() {
                    continue;
                }
                match var.space {
                    naga::AddressSpace::Immediate => {
                        immediate_bytes = module.types[var.ty].inner.size(module.to_ctx());
                    }
                    naga::AddressSpace::Storage { .. } | naga::AddressSpace::Uniform if var.binding.is_some() => {
                        let b = var.binding.as_ref().unwrap();
                        assert!(b.group == 0, "{}: {}: only @group(0) is supported", path.display(), ep.name);
                        let kind = match var.space {
                            naga::AddressSpace::Storage { access } if access.contains(naga::StorageAccess::STORE) => "StorageReadWrite",
                            naga::AddressSpace::Storage { .. } => "StorageRead",
                            _ => "Uniform",
                        };
                        let name = var.name.clone().unwrap_or_default();
                        float_atomics |= uses_float_atomics(&module, var.ty);
                        // Bytes of the type, or of one element of a runtime-sized array.
                        let bytes = match &module.types[var.ty].inner {
                            naga::TypeInner::Array { stride, size: naga::ArraySize::Dynamic, .. } => *stride,
                            inner => inner.size(module.to_ctx()),
                        };
                        bindings.push((b.binding, kind, name, type_name(&module, var.ty), bytes));
                    }
                    naga::AddressSpace::Storage { .. } | naga::AddressSpace::Uniform | naga::AddressSpace::Handle => {
                        panic!("{}: {}: resource without @binding", path.display(), ep.name)
                    }
                    _ => {}
                }
            }
            bindings.sort_by_key(|b| b.0);
            let variant = format!("{}{}", camel(&stem), camel(&ep.name));
            writeln!(variants, "    /// `kernels/{stem}.wgsl`, entry point `{}`.\n    {variant} = {count},", ep.name).unwrap();
            writeln!(all, "    Kernel::{variant},").unwrap();
            let [x, y, z] = ep.workgroup_size;
            write!(
                table,
                "    KernelInfo {{\n        name: \"{stem}.{}\",\n        file: \"{stem}\",\n        entry: \"{}\",\n        workgroup_size: [{x}, {y}, {z}],\n        immediate_bytes: {immediate_bytes},\n        float_atomics: {float_atomics},\n        bindings: &[",
                ep.name, ep.name
            )
            .unwrap();
            for (binding, kind, name, ty, bytes) in &bindings {
                write!(
                    table,
                    "BindingInfo {{ binding: {binding}, kind: BindingKind::{kind}, name: \"{name}\", ty: \"{ty}\", bytes: {bytes} }}, "
                )
                .unwrap();
            }
            writeln!(table, "],\n        spirv: include_bytes!(concat!(env!(\"OUT_DIR\"), \"/{spv_name}\")),\n    }},").unwrap();
            count += 1;
        }
    }
    let generated = format!(
        "// @generated by build.rs from kernels/*.wgsl: do not edit.\n\n\
         /// Every compute kernel, in the order of [`KERNELS`].\n\
         #[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]\n\
         #[repr(usize)]\n\
         pub enum Kernel {{\n{variants}}}\n\n\
         /// Number of kernels.\n\
         pub const KERNEL_COUNT: usize = {count};\n\n\
         /// The kernel table, indexed by [`Kernel`].\n\
         pub static KERNELS: [KernelInfo; KERNEL_COUNT] = [\n{table}];\n\n\
         static ALL_KERNELS: [Kernel; KERNEL_COUNT] = [\n{all}];\n"
    );
    std::fs::write(out_dir.join("kernels.rs"), generated).expect("write kernel table");
}

fn camel(s: &str) -> String {
    s.split('_')
        .filter(|w| !w.is_empty())
        .map(|w| {
            let mut c = w.chars();
            let first = c.next().unwrap().to_ascii_uppercase();
            std::iter::once(first).chain(c).collect::<String>()
        })
        .collect()
}

fn type_name(module: &naga::Module, ty: naga::Handle<naga::Type>) -> String {
    let t = &module.types[ty];
    if let Some(name) = &t.name {
        return name.clone();
    }
    match &t.inner {
        naga::TypeInner::Scalar(s) => scalar_name(s),
        naga::TypeInner::Atomic(s) => format!("atomic<{}>", scalar_name(s)),
        naga::TypeInner::Vector { size, scalar } => format!("vec{}<{}>", *size as u8, scalar_name(scalar)),
        naga::TypeInner::Array { base, size, .. } => match size {
            naga::ArraySize::Constant(n) => format!("array<{}, {n}>", type_name(module, *base)),
            _ => format!("array<{}>", type_name(module, *base)),
        },
        other => format!("{other:?}"),
    }
}

/// Whether a binding's type holds `atomic<f32>` (the kernel needs VK_EXT_shader_atomic_float).
fn uses_float_atomics(module: &naga::Module, ty: naga::Handle<naga::Type>) -> bool {
    match &module.types[ty].inner {
        naga::TypeInner::Atomic(s) => s.kind == naga::ScalarKind::Float,
        naga::TypeInner::Array { base, .. } => uses_float_atomics(module, *base),
        naga::TypeInner::Struct { members, .. } => members.iter().any(|m| uses_float_atomics(module, m.ty)),
        _ => false,
    }
}

fn scalar_name(s: &naga::Scalar) -> String {
    let k = match s.kind {
        naga::ScalarKind::Sint => "i",
        naga::ScalarKind::Uint => "u",
        naga::ScalarKind::Float => "f",
        naga::ScalarKind::Bool => return "bool".into(),
        _ => "?",
    };
    format!("{k}{}", s.width * 8)
}

/// `source` with each line `//!include NAME` replaced by `shared/NAME` (code two kernels share;
/// not compiled on its own).
fn with_includes(source: &str, shared: &std::path::Path) -> String {
    let mut out = String::with_capacity(source.len());
    for line in source.lines() {
        match line.strip_prefix("//!include ") {
            Some(name) => {
                let path = shared.join(name.trim());
                println!("cargo:rerun-if-changed={}", path.display());
                out.push_str(&std::fs::read_to_string(&path).unwrap_or_else(|e| panic!("{}: {e}", path.display())));
            }
            None => out.push_str(line),
        }
        out.push('\n');
    }
    out
}
