//! The front camera: what DeepRacer's car sees, rendered with wgpu (a GPU, or Mesa's lavapipe
//! without one), many environments per submission.
//!
//! The scene is built from a track's waypoints: the floor with the world's surface look
//! (procedural: asphalt, carpet, concrete, wood), the road between the borders, white border
//! lines and a dashed centre line; a race's obstacles and bot cars stand on it as solid
//! boxes (a box 0.40 × 0.30 × 0.25 m in the simapp's brown; a car of DeepRacer's footprint,
//! a dark body under a light shell). The camera sits where DeepRacer mounts it (simapp's car
//! URDF and `racecar.gazebo`): 0.137 m ahead of the car origin, 0.143 m up, pitched 15° down,
//! horizontal field of view 1.13 rad, 160×120. Frames are grayscale with DeepRacer's luma
//! (0.2989 R + 0.5870 G + 0.1140 B) unless RGB is asked for.
//!
//! Batching: every view of a call is drawn into its own viewport of one atlas texture in one
//! render pass, one submission, one readback. Each view draws only the quads in its field of
//! view, nearest layer first (the objects, nearest first and only their faces that look at
//! the camera, then the track's layers), and a stencil test shades every pixel once.

use bytemuck::{Pod, Zeroable};
use std::collections::HashMap;
use std::sync::Mutex;
use tracks::{Lighting, P2, Surface, Track};

/// Frame width (pixels).
pub const WIDTH: u32 = 160;
/// Frame height (pixels).
pub const HEIGHT: u32 = 120;
/// Horizontal field of view (rad).
pub const HFOV: f64 = 1.13;
/// Camera position ahead of the car origin (m): zed_camera_link 0.0917 + camera_link 0.044755.
pub const CAMERA_AHEAD: f64 = 0.0917 + 0.044755;
/// Camera height above the ground (m): chassis 0.023249 + 0.08 + 0.04.
pub const CAMERA_HEIGHT: f64 = 0.023249 + 0.08 + 0.04;
/// Camera pitch, down (rad).
pub const CAMERA_PITCH: f64 = 0.2618;
/// Each stereo camera's offset to the side of the car's axis (m): DeepRacer's stereo URDF
/// mounts them at y = ±0.03, a 0.06 m baseline.
pub const STEREO_OFFSET: f64 = 0.03;

/// The pose whose camera is the stereo camera `lateral` metres to the left (negative: right)
/// of the one at `pose`.
pub fn beside(pose: [f64; 3], lateral: f64) -> [f64; 3] {
    [pose[0] - lateral * pose[2].sin(), pose[1] + lateral * pose[2].cos(), pose[2]]
}
const ATLAS_COLUMNS: u32 = 8;

/// Why rendering is not possible.
#[derive(Debug, thiserror::Error)]
pub enum RenderError {
    /// No adapter: no GPU and no software Vulkan.
    #[error(
        "no graphics adapter found: install Mesa's software Vulkan (apt-get install mesa-vulkan-drivers) or run on a machine with a GPU ({0})"
    )]
    NoAdapter(String),
    /// The device refused.
    #[error("the graphics device failed: {0}")]
    Device(String),
}

/// Track meshes the renderer keeps before it drops those no view in hand uses.
const MESHES_KEPT: usize = 64;

/// One camera view to render.
#[derive(Clone, Debug)]
pub struct View<'a> {
    /// The track (its geometry is built once and cached by name and direction).
    pub track: &'a Track,
    /// The floor's look.
    pub surface: Surface,
    /// Lighting.
    pub lighting: Lighting,
    /// Car origin x, y (m) and yaw (rad).
    pub pose: [f64; 3],
    /// Extra camera height (m) and pitch (rad), for domain randomisation.
    pub jitter: [f64; 2],
    /// Seed of the surface texture variation (0 = the world's own look).
    pub texture_seed: u32,
    /// The race's obstacles and bots (empty in a time trial).
    pub objects: &'a [crate::objects::Object],
}

#[repr(C)]
#[derive(Clone, Copy, Pod, Zeroable)]
struct Vertex {
    pos: [f32; 3],
    kind: f32,
}

#[repr(C)]
#[derive(Clone, Copy, Pod, Zeroable)]
struct Uniform {
    view_proj: [[f32; 4]; 4],
    /// surface id, light intensity, texture seed, light elevation (rad)
    params: [f32; 4],
    /// Offset of world coordinates (keeps f32 precision near the track).
    origin: [f32; 4],
}

const UNIFORM_STRIDE: u64 = 256;

/// Stencil rule: draw where nothing has been drawn yet, and mark the pixel.
const ONCE: wgpu::StencilFaceState = wgpu::StencilFaceState {
    compare: wgpu::CompareFunction::Equal,
    fail_op: wgpu::StencilOperation::Keep,
    depth_fail_op: wgpu::StencilOperation::Keep,
    pass_op: wgpu::StencilOperation::IncrementClamp,
};

/// A renderer for batches of camera views.
pub struct Renderer {
    device: wgpu::Device,
    queue: wgpu::Queue,
    pipeline: wgpu::RenderPipeline,
    layout: wgpu::BindGroupLayout,
    meshes: HashMap<String, (wgpu::Buffer, Vec<Item>)>,
    indices: Option<(wgpu::Buffer, u64)>,
    object_vertices: Option<(wgpu::Buffer, u64)>,
    capacity: u32,
    target: Option<(wgpu::Texture, wgpu::Buffer, wgpu::Buffer, wgpu::BindGroup, wgpu::Texture)>,
    adapter: String,
}

const SHADER: &str = r#"
struct U { view_proj: mat4x4<f32>, params: vec4<f32>, origin: vec4<f32> };
@group(0) @binding(0) var<uniform> u: U;

struct VOut { @builtin(position) clip: vec4<f32>, @location(0) world: vec2<f32>, @location(1) kind: f32 };

@vertex
fn vs(@location(0) pos: vec3<f32>, @location(1) kind: f32) -> VOut {
    var o: VOut;
    o.clip = u.view_proj * vec4<f32>(pos - u.origin.xyz, 1.0);
    o.world = pos.xy;
    o.kind = kind;
    return o;
}

fn hash(p: vec2<f32>) -> f32 {
    let q = fract(p * vec2<f32>(123.34, 456.21));
    let r = q + dot(q, q + 45.32);
    return fract(r.x * r.y);
}

fn vnoise(p: vec2<f32>) -> f32 {
    let i = floor(p);
    let f = fract(p);
    let s = f * f * (3.0 - 2.0 * f);
    let a = hash(i);
    let b = hash(i + vec2<f32>(1.0, 0.0));
    let c = hash(i + vec2<f32>(0.0, 1.0));
    let d = hash(i + vec2<f32>(1.0, 1.0));
    return mix(mix(a, b, s.x), mix(c, d, s.x), s.y);
}

fn surface(p: vec2<f32>, id: f32, seed: f32) -> vec3<f32> {
    let q = p + vec2<f32>(seed * 17.0, seed * 31.0);
    if (id < 0.5) {
        // asphalt-like mat: dark, fine speckle
        return vec3<f32>(0.30, 0.31, 0.32) + 0.08 * (hash(floor(q * 200.0)) - 0.5);
    } else if (id < 1.5) {
        // carpet: blue-grey tiles with a fibrous texture
        let tile = step(0.5, fract(floor(q.x * 2.0) * 0.5 + floor(q.y * 2.0) * 0.5));
        return vec3<f32>(0.22, 0.26, 0.36) + 0.06 * tile + 0.10 * (vnoise(q * 90.0) - 0.5);
    } else if (id < 2.5) {
        // concrete: light grey with soft blotches
        return vec3<f32>(0.62, 0.62, 0.60) + 0.14 * (vnoise(q * 3.0) - 0.5) + 0.05 * (vnoise(q * 40.0) - 0.5);
    }
    // wood: warm planks (0.15 m wide) with grain along them
    let plank = floor(q.y / 0.15);
    let tone = 0.10 * (hash(vec2<f32>(plank, 3.0)) - 0.5);
    let grain = 0.08 * sin(q.x * 40.0 + 6.0 * vnoise(vec2<f32>(q.x * 2.0, plank)));
    let seam = 0.15 * step(0.96, fract(q.y / 0.15));
    return vec3<f32>(0.62, 0.43, 0.25) + tone + grain - seam;
}

@fragment
fn fs(i: VOut) -> @location(0) vec4<f32> {
    var c: vec3<f32>;
    if (i.kind < 0.5) {
        c = surface(i.world, u.params.x, u.params.z);
    } else if (i.kind < 1.5) {
        c = vec3<f32>(0.18, 0.18, 0.19) + 0.03 * (hash(floor(i.world * 150.0)) - 0.5);
    } else if (i.kind < 2.5) {
        c = vec3<f32>(0.95, 0.95, 0.95);
    } else if (i.kind < 3.5) {
        c = vec3<f32>(0.95, 0.80, 0.15);
    } else {
        // Objects: the material is the whole part of `kind`, the face's shade its fraction.
        let m = floor(i.kind);
        let shade = 0.45 + fract(i.kind);
        if (m < 4.5) {
            c = vec3<f32>(0.482, 0.380, 0.310) * shade;
        } else if (m < 5.5) {
            c = vec3<f32>(0.08, 0.08, 0.09) * shade;
        } else {
            c = vec3<f32>(0.80, 0.80, 0.82) * shade;
        }
    }
    // A flat world under a directional light: brightness follows the light's elevation.
    let light = u.params.y * (0.45 + 0.55 * sin(u.params.w));
    return vec4<f32>(clamp(c * light, vec3<f32>(0.0), vec3<f32>(1.0)), 1.0);
}
"#;

fn surface_id(s: Surface) -> f32 {
    match s {
        Surface::Asphalt => 0.0,
        Surface::Carpet => 1.0,
        Surface::Concrete => 2.0,
        Surface::Wood => 3.0,
    }
}

/// The track's triangles: floor, road, borders, centre dashes (in drawing order).
fn mesh(track: &Track) -> Vec<Vertex> {
    let mut v = Vec::new();
    let mut quad = |a: P2, b: P2, c: P2, d: P2, z: f32, kind: f32| {
        for p in [a, b, c, a, c, d] {
            v.push(Vertex { pos: [p.x as f32, p.y as f32, z], kind });
        }
    };
    let pts = track.inner().points().iter().chain(track.outer().points());
    let (mut lo, mut hi) = (P2::new(f64::MAX, f64::MAX), P2::new(f64::MIN, f64::MIN));
    for p in pts {
        lo = lo.inf(p);
        hi = hi.sup(p);
    }
    let m = 30.0;
    quad(
        P2::new(lo.x - m, lo.y - m),
        P2::new(hi.x + m, lo.y - m),
        P2::new(hi.x + m, hi.y + m),
        P2::new(lo.x - m, hi.y + m),
        0.0,
        0.0,
    );
    let (inner, outer) = (track.inner().points(), track.outer().points());
    for i in 0..inner.len() - 1 {
        quad(inner[i], outer[i], outer[i + 1], inner[i + 1], 0.0, 1.0);
    }
    // A band of width 2·half along a border line.
    let strip = |line: &[P2], half: f64, quad: &mut dyn FnMut(P2, P2, P2, P2, f32, f32), kind: f32| {
        for w in line.windows(2) {
            let d = w[1] - w[0];
            let len = d.norm();
            if len < 1e-9 {
                continue;
            }
            let n = nalgebra::Vector2::new(-d.y, d.x) / len * half;
            quad(w[0] - n, w[1] - n, w[1] + n, w[0] + n, 0.0, kind);
        }
    };
    strip(inner, 0.025, &mut quad, 2.0);
    strip(outer, 0.025, &mut quad, 2.0);
    // Dashes: 0.15 m on, 0.15 m off, along the centre line.
    let len = track.length();
    let mut s = 0.0;
    while s + 0.15 <= len {
        let (a, _) = track.pose_at(s);
        let (b, _) = track.pose_at(s + 0.15);
        let d = b - a;
        if d.norm() > 1e-9 {
            let n = nalgebra::Vector2::new(-d.y, d.x) / d.norm() * 0.01;
            quad(a - n, b - n, b + n, a + n, 0.0, 3.0);
        }
        s += 0.3;
    }
    v
}

/// Objects' materials (the `kind` the shader reads).
const BOX: f32 = 4.0;
const CAR_BODY: f32 = 5.0;
const CAR_SHELL: f32 = 6.0;
/// The box obstacle's size, along × across × height (m): the simapp's `box_obstacle` model.
pub const BOX_SIZE: [f64; 3] = [0.40, 0.30, 0.25];

/// The triangles of the objects a camera at `pose` sees, nearest first: each object's solid
/// boxes (a car's shell before its body, which it stands on), only the faces turned to the
/// camera, so that no face of one box hides another of it.
fn object_triangles(objects: &[crate::objects::Object], pose: [f64; 3], jitter: [f64; 2], out: &mut Vec<Vertex>) {
    let (c, s) = (pose[2].cos(), pose[2].sin());
    let eye = [pose[0] + CAMERA_AHEAD * c, pose[1] + CAMERA_AHEAD * s, CAMERA_HEIGHT + jitter[0]];
    let mut near: Vec<(f64, &crate::objects::Object)> = objects
        .iter()
        .filter_map(|o| {
            let (dx, dy) = (o.pose.position.x - eye[0], o.pose.position.y - eye[1]);
            // Behind the camera or far off: not drawn.
            (dx * c + dy * s > -0.4 && dx * dx + dy * dy < 400.0).then_some((dx * dx + dy * dy, o))
        })
        .collect();
    near.sort_by(|a, b| a.0.total_cmp(&b.0));
    for (_, o) in near {
        let (along, across) = (o.footprint.1, o.footprint.0);
        if o.car {
            solid(out, eye, o, [along * 0.8, across * 0.85], [0.09, 0.15], CAR_SHELL);
            solid(out, eye, o, [along, across], [0.02, 0.09], CAR_BODY);
        } else {
            solid(out, eye, o, [BOX_SIZE[0], BOX_SIZE[1]], [0.0, BOX_SIZE[2]], BOX);
        }
    }
}

/// A box of `size` (along × across) from height `z[0]` to `z[1]`, centred on the object:
/// its top and sides that face `eye`.
fn solid(out: &mut Vec<Vertex>, eye: [f64; 3], o: &crate::objects::Object, size: [f64; 2], z: [f64; 2], kind: f32) {
    let (s, c) = o.pose.heading.sin_cos();
    let at = o.pose.position;
    let corner = |x: f64, y: f64| [at.x + x * c - y * s, at.y + x * s + y * c];
    let (hl, hw) = (size[0] / 2.0, size[1] / 2.0);
    let b = [corner(hl, hw), corner(-hl, hw), corner(-hl, -hw), corner(hl, -hw)];
    let mut quad = |q: [[f64; 3]; 4], shade: f32| {
        for k in [0, 1, 2, 0, 2, 3] {
            out.push(Vertex { pos: [q[k][0] as f32, q[k][1] as f32, q[k][2] as f32], kind: kind + shade });
        }
    };
    if eye[2] > z[1] {
        quad(b.map(|p| [p[0], p[1], z[1]]), 0.5);
    }
    for i in 0..4 {
        let (p, q) = (b[i], b[(i + 1) % 4]);
        // The outward normal of the side from p to q (corners run counter-clockwise).
        let n = [q[1] - p[1], -(q[0] - p[0])];
        if (eye[0] - p[0]) * n[0] + (eye[1] - p[1]) * n[1] > 0.0 {
            let shade = if i % 2 == 0 { 0.3 } else { 0.2 };
            quad([[p[0], p[1], z[0]], [q[0], q[1], z[0]], [q[0], q[1], z[1]], [p[0], p[1], z[1]]], shade);
        }
    }
}

/// Write `bytes` to the buffer in `slot`, first growing it (to a power of two, at least
/// 4 KiB) when it is missing or too small.
fn upload(
    device: &wgpu::Device,
    queue: &wgpu::Queue,
    slot: &mut Option<(wgpu::Buffer, u64)>,
    bytes: &[u8],
    usage: wgpu::BufferUsages,
    label: &str,
) {
    let len = bytes.len() as u64;
    if slot.as_ref().is_none_or(|(_, cap)| *cap < len) {
        let cap = len.next_power_of_two().max(4096);
        let buf = device.create_buffer(&wgpu::BufferDescriptor {
            label: Some(label),
            size: cap,
            usage,
            mapped_at_creation: false,
        });
        *slot = Some((buf, cap));
    }
    queue.write_buffer(&slot.as_ref().expect("made above").0, 0, bytes);
}

/// A quad's bounding circle in the plane, for culling.
#[derive(Clone, Copy)]
struct Item {
    center: [f32; 2],
    radius: f32,
}

/// Bounding circles of the mesh's quads (6 vertices each), in mesh order.
fn items(v: &[Vertex]) -> Vec<Item> {
    v.chunks(6)
        .map(|q| {
            let (mut cx, mut cy) = (0.0f32, 0.0f32);
            for p in q {
                cx += p.pos[0] / 6.0;
                cy += p.pos[1] / 6.0;
            }
            let r = q.iter().map(|p| ((p.pos[0] - cx).powi(2) + (p.pos[1] - cy).powi(2)).sqrt()).fold(0.0, f32::max);
            Item { center: [cx, cy], radius: r }
        })
        .collect()
}

/// Indices of the quads a camera at `pose` can see (the floor always), nearest layer first
/// (dashes, borders, road, floor: the reverse of the mesh's order), for the stencil.
fn visible(items: &[Item], pose: [f64; 3], out: &mut Vec<u32>) {
    let (c, s) = (pose[2].cos() as f32, pose[2].sin() as f32);
    let cam = [pose[0] as f32 + CAMERA_AHEAD as f32 * c, pose[1] as f32 + CAMERA_AHEAD as f32 * s];
    let half = (HFOV / 2.0) as f32 + 0.05;
    for (k, it) in items.iter().enumerate().rev() {
        let keep = k == 0 || {
            let (dx, dy) = (it.center[0] - cam[0], it.center[1] - cam[1]);
            let d = (dx * dx + dy * dy).sqrt();
            if d <= it.radius + 0.3 {
                true
            } else {
                let ahead = dx * c + dy * s;
                let side = -dx * s + dy * c;
                // Inside the horizontal field of view widened by the quad's size.
                ahead > -it.radius && side.abs().atan2(ahead) <= half + (it.radius / d).min(1.0).asin()
            }
        };
        if keep {
            let f = k as u32 * 6;
            out.extend(f..f + 6);
        }
    }
}

/// The view-projection matrix for a camera pose (wgpu clip space, z in [0, 1]), relative to
/// `origin`.
fn view_proj(pose: [f64; 3], jitter: [f64; 2], origin: [f64; 2]) -> [[f32; 4]; 4] {
    use nalgebra::{Matrix4, Point3, Vector3};
    let (c, s) = (pose[2].cos(), pose[2].sin());
    let eye = Point3::new(
        pose[0] - origin[0] + CAMERA_AHEAD * c,
        pose[1] - origin[1] + CAMERA_AHEAD * s,
        CAMERA_HEIGHT + jitter[0],
    );
    let pitch = CAMERA_PITCH + jitter[1];
    let dir = Vector3::new(c * pitch.cos(), s * pitch.cos(), -pitch.sin());
    let view = Matrix4::look_at_rh(&eye, &(eye + dir), &Vector3::z());
    let aspect = WIDTH as f64 / HEIGHT as f64;
    let vfov = 2.0 * ((HFOV / 2.0).tan() / aspect).atan();
    let proj = Matrix4::new_perspective(aspect, vfov, 0.02, 60.0);
    // OpenGL depth [-1, 1] to wgpu's [0, 1].
    let fix = Matrix4::new(1.0, 0.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 0.0, 0.5, 0.5, 0.0, 0.0, 0.0, 1.0);
    let m: Matrix4<f32> = (fix * proj * view).cast();
    let mut out = [[0.0f32; 4]; 4];
    for (col, o) in out.iter_mut().enumerate() {
        for (row, x) in o.iter_mut().enumerate() {
            *x = m[(row, col)];
        }
    }
    out
}

/// Renderers the process's environments used and gave back: each holds a device, its
/// pipeline and its track meshes, and making one per evaluation would build them again and
/// again (and the driver may keep what each device allocated).
static POOL: Mutex<Vec<Renderer>> = Mutex::new(Vec::new());

/// A renderer lent from the process's pool ([`Renderer::pooled`]); it goes back when dropped.
pub struct Pooled(Option<Renderer>);

impl std::ops::Deref for Pooled {
    type Target = Renderer;
    fn deref(&self) -> &Renderer {
        self.0.as_ref().expect("lent until dropped")
    }
}

impl std::ops::DerefMut for Pooled {
    fn deref_mut(&mut self) -> &mut Renderer {
        self.0.as_mut().expect("lent until dropped")
    }
}

impl Drop for Pooled {
    fn drop(&mut self) {
        if let Some(r) = self.0.take() {
            POOL.lock().unwrap_or_else(|e| e.into_inner()).push(r);
        }
    }
}

impl Renderer {
    /// A renderer from the process's pool, or a new one when every pooled one is lent: a
    /// process holds as many as it ever used at once (training and an evaluation: two).
    pub fn pooled() -> Result<Pooled, RenderError> {
        let kept = POOL.lock().unwrap_or_else(|e| e.into_inner()).pop();
        Ok(Pooled(Some(match kept {
            Some(r) => r,
            None => Renderer::new()?,
        })))
    }

    /// Open the best adapter (a GPU if there is one, else lavapipe).
    pub fn new() -> Result<Renderer, RenderError> {
        let instance = wgpu::Instance::new(wgpu::InstanceDescriptor::new_without_display_handle_from_env());
        let adapter = pollster::block_on(instance.request_adapter(&wgpu::RequestAdapterOptions {
            power_preference: wgpu::PowerPreference::HighPerformance,
            force_fallback_adapter: false,
            compatible_surface: None,
            apply_limit_buckets: false,
        }))
        .map_err(|e| RenderError::NoAdapter(e.to_string()))?;
        let info = adapter.get_info();
        let adapter_name = format!("{} ({:?}, {:?})", info.name, info.device_type, info.backend);
        let (device, queue) = pollster::block_on(adapter.request_device(&wgpu::DeviceDescriptor {
            label: Some("paddock camera"),
            required_features: wgpu::Features::empty(),
            required_limits: wgpu::Limits::downlevel_defaults(),
            experimental_features: wgpu::ExperimentalFeatures::disabled(),
            memory_hints: wgpu::MemoryHints::Performance,
            trace: wgpu::Trace::Off,
        }))
        .map_err(|e| RenderError::Device(e.to_string()))?;
        let module = device.create_shader_module(wgpu::ShaderModuleDescriptor {
            label: Some("camera"),
            source: wgpu::ShaderSource::Wgsl(SHADER.into()),
        });
        let layout = device.create_bind_group_layout(&wgpu::BindGroupLayoutDescriptor {
            label: None,
            entries: &[wgpu::BindGroupLayoutEntry {
                binding: 0,
                visibility: wgpu::ShaderStages::VERTEX_FRAGMENT,
                ty: wgpu::BindingType::Buffer {
                    ty: wgpu::BufferBindingType::Uniform,
                    has_dynamic_offset: true,
                    min_binding_size: wgpu::BufferSize::new(std::mem::size_of::<Uniform>() as u64),
                },
                count: None,
            }],
        });
        let pl = device.create_pipeline_layout(&wgpu::PipelineLayoutDescriptor {
            label: None,
            bind_group_layouts: &[Some(&layout)],
            immediate_size: 0,
        });
        let pipeline = device.create_render_pipeline(&wgpu::RenderPipelineDescriptor {
            label: Some("camera"),
            layout: Some(&pl),
            vertex: wgpu::VertexState {
                module: &module,
                entry_point: Some("vs"),
                compilation_options: Default::default(),
                buffers: &[Some(wgpu::VertexBufferLayout {
                    array_stride: std::mem::size_of::<Vertex>() as u64,
                    step_mode: wgpu::VertexStepMode::Vertex,
                    attributes: &wgpu::vertex_attr_array![0 => Float32x3, 1 => Float32],
                })],
            },
            primitive: wgpu::PrimitiveState { cull_mode: None, ..Default::default() },
            // Each pixel is shaded once: the nearest layer is drawn first (lines, road, then the
            // floor) and a pixel's stencil, once set, rejects later fragments before shading.
            depth_stencil: Some(wgpu::DepthStencilState::stencil(
                wgpu::TextureFormat::Stencil8,
                wgpu::StencilState { front: ONCE, back: ONCE, read_mask: 0xff, write_mask: 0xff },
            )),
            multisample: wgpu::MultisampleState::default(),
            fragment: Some(wgpu::FragmentState {
                module: &module,
                entry_point: Some("fs"),
                compilation_options: Default::default(),
                targets: &[Some(wgpu::ColorTargetState {
                    format: wgpu::TextureFormat::Rgba8Unorm,
                    blend: None,
                    write_mask: wgpu::ColorWrites::ALL,
                })],
            }),
            multiview_mask: None,
            cache: None,
        });
        Ok(Renderer {
            device,
            queue,
            pipeline,
            layout,
            meshes: HashMap::new(),
            indices: None,
            object_vertices: None,
            capacity: 0,
            target: None,
            adapter: adapter_name,
        })
    }

    /// The adapter in use (e.g. "llvmpipe (LLVM 15…) (Cpu, Vulkan)").
    pub fn adapter(&self) -> &str {
        &self.adapter
    }

    fn ensure(&mut self, n: u32) {
        if self.capacity >= n && self.target.is_some() {
            return;
        }
        let cap = n.max(1).next_power_of_two();
        let rows = cap.div_ceil(ATLAS_COLUMNS);
        let (w, h) = (ATLAS_COLUMNS.min(cap) * WIDTH, rows * HEIGHT);
        let texture = self.device.create_texture(&wgpu::TextureDescriptor {
            label: Some("atlas"),
            size: wgpu::Extent3d { width: w, height: h, depth_or_array_layers: 1 },
            mip_level_count: 1,
            sample_count: 1,
            dimension: wgpu::TextureDimension::D2,
            format: wgpu::TextureFormat::Rgba8Unorm,
            usage: wgpu::TextureUsages::RENDER_ATTACHMENT | wgpu::TextureUsages::COPY_SRC,
            view_formats: &[],
        });
        let padded = (w * 4).div_ceil(wgpu::COPY_BYTES_PER_ROW_ALIGNMENT) * wgpu::COPY_BYTES_PER_ROW_ALIGNMENT;
        let readback = self.device.create_buffer(&wgpu::BufferDescriptor {
            label: Some("readback"),
            size: padded as u64 * h as u64,
            usage: wgpu::BufferUsages::COPY_DST | wgpu::BufferUsages::MAP_READ,
            mapped_at_creation: false,
        });
        let uniforms = self.device.create_buffer(&wgpu::BufferDescriptor {
            label: Some("uniforms"),
            size: UNIFORM_STRIDE * cap as u64,
            usage: wgpu::BufferUsages::UNIFORM | wgpu::BufferUsages::COPY_DST,
            mapped_at_creation: false,
        });
        let bind = self.device.create_bind_group(&wgpu::BindGroupDescriptor {
            label: None,
            layout: &self.layout,
            entries: &[wgpu::BindGroupEntry {
                binding: 0,
                resource: wgpu::BindingResource::Buffer(wgpu::BufferBinding {
                    buffer: &uniforms,
                    offset: 0,
                    size: wgpu::BufferSize::new(std::mem::size_of::<Uniform>() as u64),
                }),
            }],
        });
        let stencil = self.device.create_texture(&wgpu::TextureDescriptor {
            label: Some("stencil"),
            size: wgpu::Extent3d { width: w, height: h, depth_or_array_layers: 1 },
            mip_level_count: 1,
            sample_count: 1,
            dimension: wgpu::TextureDimension::D2,
            format: wgpu::TextureFormat::Stencil8,
            usage: wgpu::TextureUsages::RENDER_ATTACHMENT,
            view_formats: &[],
        });
        self.capacity = cap;
        self.target = Some((texture, readback, uniforms, bind, stencil));
    }

    fn mesh_for(&mut self, track: &Track) -> String {
        let key = format!("{}/{:?}", track.name(), track.direction());
        if !self.meshes.contains_key(&key) {
            use wgpu::util::DeviceExt;
            let v = mesh(track);
            let buf = self.device.create_buffer_init(&wgpu::util::BufferInitDescriptor {
                label: Some("track"),
                contents: bytemuck::cast_slice(&v),
                usage: wgpu::BufferUsages::VERTEX,
            });
            self.meshes.insert(key.clone(), (buf, items(&v)));
        }
        key
    }

    /// Render the views; returns `views.len()` frames of 160×120, row-major, top row first:
    /// grayscale (1 byte per pixel) or RGB (3 bytes) when `rgb`.
    pub fn render(&mut self, views: &[View<'_>], rgb: bool) -> Vec<u8> {
        self.render_some(views, None, rgb)
    }

    /// [`Renderer::render`], drawing only the views `drawn` marks (every one with `None`): each
    /// view keeps its place in the atlas, and so the bits it would have drawn with the others;
    /// the frames of the views not drawn are black.
    pub fn render_some(&mut self, views: &[View<'_>], drawn: Option<&[bool]>, rgb: bool) -> Vec<u8> {
        let n = views.len() as u32;
        if let Some(d) = drawn {
            assert_eq!(d.len(), views.len(), "one mark per view");
        }
        let on = |i: usize| drawn.is_none_or(|d| d[i]);
        self.ensure(n);
        let keys: Vec<String> = views.iter().map(|v| self.mesh_for(v.track)).collect();
        // Generated worlds bring a new track every few episodes: meshes no view uses go.
        if self.meshes.len() > MESHES_KEPT {
            self.meshes.retain(|k, _| keys.contains(k));
        }
        // Only what each camera can see: most of a track is behind or beside the car.
        let mut indices: Vec<u32> = Vec::new();
        let mut ranges = Vec::with_capacity(views.len());
        for (i, (v, key)) in views.iter().zip(&keys).enumerate() {
            let start = indices.len() as u32;
            if on(i) {
                visible(&self.meshes[key].1, v.pose, &mut indices);
            }
            ranges.push(start..indices.len() as u32);
        }
        let mut object_vertices: Vec<Vertex> = Vec::new();
        let mut object_ranges = Vec::with_capacity(views.len());
        for (i, v) in views.iter().enumerate() {
            let start = object_vertices.len() as u32;
            if on(i) {
                object_triangles(v.objects, v.pose, v.jitter, &mut object_vertices);
            }
            object_ranges.push(start..object_vertices.len() as u32);
        }
        if !object_vertices.is_empty() {
            let bytes: &[u8] = bytemuck::cast_slice(&object_vertices);
            let usage = wgpu::BufferUsages::VERTEX | wgpu::BufferUsages::COPY_DST;
            upload(&self.device, &self.queue, &mut self.object_vertices, bytes, usage, "objects");
        }
        let usage = wgpu::BufferUsages::INDEX | wgpu::BufferUsages::COPY_DST;
        upload(&self.device, &self.queue, &mut self.indices, bytemuck::cast_slice(&indices), usage, "indices");
        let (ibuf, _) = self.indices.as_ref().expect("uploaded above");
        let (texture, readback, uniforms, bind, stencil) = self.target.as_ref().expect("ensured");
        let stencil_view = stencil.create_view(&wgpu::TextureViewDescriptor::default());
        let mut data = vec![0u8; (UNIFORM_STRIDE * n as u64) as usize];
        for (i, v) in views.iter().enumerate() {
            let origin = [v.pose[0].floor(), v.pose[1].floor()];
            let u = Uniform {
                view_proj: view_proj(v.pose, v.jitter, origin),
                params: [
                    surface_id(v.surface),
                    v.lighting.intensity as f32,
                    v.texture_seed as f32 * 0.1,
                    v.lighting.elevation_deg.to_radians() as f32,
                ],
                origin: [origin[0] as f32, origin[1] as f32, 0.0, 0.0],
            };
            let off = i * UNIFORM_STRIDE as usize;
            data[off..off + std::mem::size_of::<Uniform>()].copy_from_slice(bytemuck::bytes_of(&u));
        }
        self.queue.write_buffer(uniforms, 0, &data);
        let view = texture.create_view(&wgpu::TextureViewDescriptor::default());
        let mut enc = self.device.create_command_encoder(&wgpu::CommandEncoderDescriptor { label: None });
        {
            let mut pass = enc.begin_render_pass(&wgpu::RenderPassDescriptor {
                label: Some("atlas"),
                color_attachments: &[Some(wgpu::RenderPassColorAttachment {
                    view: &view,
                    depth_slice: None,
                    resolve_target: None,
                    ops: wgpu::Operations {
                        load: wgpu::LoadOp::Clear(wgpu::Color::BLACK),
                        store: wgpu::StoreOp::Store,
                    },
                })],
                depth_stencil_attachment: Some(wgpu::RenderPassDepthStencilAttachment {
                    view: &stencil_view,
                    depth_ops: None,
                    stencil_ops: Some(wgpu::Operations { load: wgpu::LoadOp::Clear(0), store: wgpu::StoreOp::Discard }),
                }),
                timestamp_writes: None,
                occlusion_query_set: None,
                multiview_mask: None,
            });
            pass.set_pipeline(&self.pipeline);
            pass.set_stencil_reference(0);
            pass.set_index_buffer(ibuf.slice(..), wgpu::IndexFormat::Uint32);
            for (i, key) in keys.iter().enumerate().filter(|(i, _)| on(*i)) {
                let (buf, _) = &self.meshes[key];
                let (col, row) = (i as u32 % ATLAS_COLUMNS, i as u32 / ATLAS_COLUMNS);
                pass.set_viewport((col * WIDTH) as f32, (row * HEIGHT) as f32, WIDTH as f32, HEIGHT as f32, 0.0, 1.0);
                pass.set_bind_group(0, bind, &[(i as u64 * UNIFORM_STRIDE) as u32]);
                // Objects first: they stand in front of the floor they hide.
                if let Some((obuf, _)) = self.object_vertices.as_ref().filter(|_| !object_ranges[i].is_empty()) {
                    pass.set_vertex_buffer(0, obuf.slice(..));
                    pass.draw(object_ranges[i].clone(), 0..1);
                }
                pass.set_vertex_buffer(0, buf.slice(..));
                pass.draw_indexed(ranges[i].clone(), 0, 0..1);
            }
        }
        let size = texture.size();
        let padded = (size.width * 4).div_ceil(wgpu::COPY_BYTES_PER_ROW_ALIGNMENT) * wgpu::COPY_BYTES_PER_ROW_ALIGNMENT;
        let rows_used = n.div_ceil(ATLAS_COLUMNS) * HEIGHT;
        enc.copy_texture_to_buffer(
            wgpu::TexelCopyTextureInfo {
                texture,
                mip_level: 0,
                origin: wgpu::Origin3d::ZERO,
                aspect: wgpu::TextureAspect::All,
            },
            wgpu::TexelCopyBufferInfo {
                buffer: readback,
                layout: wgpu::TexelCopyBufferLayout {
                    offset: 0,
                    bytes_per_row: Some(padded),
                    rows_per_image: Some(size.height),
                },
            },
            wgpu::Extent3d { width: size.width, height: rows_used, depth_or_array_layers: 1 },
        );
        self.queue.submit([enc.finish()]);
        let slice = readback.slice(..padded as u64 * rows_used as u64);
        slice.map_async(wgpu::MapMode::Read, |_| {});
        let _ = self.device.poll(wgpu::PollType::wait_indefinitely());
        let px = if rgb { 3 } else { 1 };
        let mut out = vec![0u8; n as usize * (WIDTH * HEIGHT) as usize * px];
        {
            use rayon::prelude::*;
            let mapped = slice.get_mapped_range().expect("mapped after the poll");
            let src: &[u8] = &mapped;
            // One view per task: pick its viewport out of the atlas, convert to luma or RGB.
            out.par_chunks_mut((WIDTH * HEIGHT) as usize * px).enumerate().filter(|(i, _)| on(*i)).for_each(
                |(i, frame)| {
                    let (col, row) = (i as u32 % ATLAS_COLUMNS, i as u32 / ATLAS_COLUMNS);
                    for y in 0..HEIGHT {
                        let at = ((row * HEIGHT + y) * padded + col * WIDTH * 4) as usize;
                        let line = &src[at..at + 4 * WIDTH as usize];
                        let dst = &mut frame[(y * WIDTH) as usize * px..((y + 1) * WIDTH) as usize * px];
                        for (x, p) in line.chunks_exact(4).enumerate() {
                            if rgb {
                                dst[3 * x..3 * x + 3].copy_from_slice(&p[..3]);
                            } else {
                                let yl = 0.2989 * p[0] as f32 + 0.5870 * p[1] as f32 + 0.1140 * p[2] as f32;
                                dst[x] = yl.round().clamp(0.0, 255.0) as u8;
                            }
                        }
                    }
                },
            );
        }
        readback.unmap();
        out
    }
}
