//! The wgpu side of the viewer: device set-up, per-scan GPU data, long-lived
//! pipelines, size-dependent targets, where f64 poses become camera-relative f32, and
//! the renderer that records every pass into a given target, one file per compositing
//! strategy (window and headless share all of it).

mod coarse;
mod pipelines;
pub mod points;
mod readback;
mod relative;
mod renderer;
mod scan_data;
pub mod shaders;
mod targets;
pub mod tonemap;

pub(crate) use pipelines::surface_pipeline;
pub use readback::{LayerReadback, read_depth_texture, read_radiance_texture, read_rgba_texture};
pub use relative::{gpu_from_pose_relative, pose_relative};
pub use renderer::{
    FrameStats, Progress, ProgressiveFrame, RenderSettings, RenderTarget, Renderer, Strategy,
};
pub(crate) use scan_data::rgba_of_rgb;
pub use scan_data::scan_gpu_bytes;
pub use targets::TargetMemory;
pub use tonemap::{RADIANCE_FORMAT, ToneMapPass, tone_map_headless, upload_radiance};

/// Formats of the per-scan layers and the pre-pass target. Integer formats hold
/// floats bit-exactly and are colour-renderable on every backend (32-bit float
/// formats are not on GL).
pub const LAYER_COLOUR_FORMAT: wgpu::TextureFormat = wgpu::TextureFormat::Rgba8Unorm;
pub const LAYER_DATA_FORMAT: wgpu::TextureFormat = wgpu::TextureFormat::Rgba32Uint;
pub const NEAREST_FORMAT: wgpu::TextureFormat = wgpu::TextureFormat::Rg32Uint;
pub const DEPTH_FORMAT: wgpu::TextureFormat = wgpu::TextureFormat::Depth32Float;
/// The renderer's depth buffer where the device can mark pixels in a stencil and run
/// the merge's stencil test before its shader ([`MARK_FEATURES`]): the same depth,
/// with the k-buffer's marks beside it.
pub const MARKED_DEPTH_FORMAT: wgpu::TextureFormat = wgpu::TextureFormat::Depth32FloatStencil8;
/// What merging only marked pixels needs: a stencil beside the f32 depth, and the
/// fragment tests forced before a shader that writes storage (otherwise they may run
/// after it, and skip nothing). Requested where the adapter has them (lavapipe and
/// most native drivers); a browser's WebGPU does not offer the second.
pub const MARK_FEATURES: wgpu::Features =
    wgpu::Features::DEPTH32FLOAT_STENCIL8.union(wgpu::Features::SHADER_EARLY_DEPTH_TEST);

/// Whether `device` can merge only marked pixels (`MARK_FEATURES`).
pub fn marks_supported(device: &wgpu::Device) -> bool {
    device.features().contains(MARK_FEATURES)
}

/// The format of the renderer's depth buffer on `device`.
pub fn scan_depth_format(device: &wgpu::Device) -> wgpu::TextureFormat {
    if marks_supported(device) {
        MARKED_DEPTH_FORMAT
    } else {
        DEPTH_FORMAT
    }
}
/// The EO texture: display (sRGB-encoded) values, sampled bilinearly as they are.
pub const EO_FORMAT: wgpu::TextureFormat = wgpu::TextureFormat::Rgba8Unorm;
/// Headless renders go to this format (PNG-ready).
pub const IMAGE_FORMAT: wgpu::TextureFormat = wgpu::TextureFormat::Rgba8Unorm;

#[derive(Debug, thiserror::Error)]
pub enum GpuError {
    #[error(
        "no GPU adapter: wgpu found no Vulkan or GL device (install Mesa's lavapipe, \
         Debian package mesa-vulkan-drivers, for a software one): {0}"
    )]
    NoAdapter(String),
    #[error("cannot open the GPU device {adapter}: {message}")]
    Device { adapter: String, message: String },
    #[error("scan {id}: EO texture {width}x{height} exceeds the device limit {limit}")]
    TextureTooLarge {
        id: u64,
        width: u32,
        height: u32,
        limit: u32,
    },
    #[error("scan {id}: EO texture size {width}x{height} does not match its {bytes} bytes")]
    BadTexture {
        id: u64,
        width: u32,
        height: u32,
        bytes: usize,
    },
    #[error("target {width}x{height} is empty or exceeds the device limit {limit}")]
    TargetSize { width: u32, height: u32, limit: u32 },
    #[error("{what} needs {bytes} bytes, over the device limit {limit}")]
    TooLarge {
        what: &'static str,
        bytes: u64,
        limit: u64,
    },
    #[error(
        "{visible} visible scans need {visible} layers, over the device limit {limit} (use the k-buffer)"
    )]
    TooManyLayers { visible: usize, limit: u32 },
    #[error(
        "{views} VDTM views need {views} texture layers, over the device limit {limit} \
         (lower the views VDTM textures from)"
    )]
    TooManyViews { views: usize, limit: u32 },
    #[error(
        "the k-buffer keeps fragments in storage buffers, which this device lacks \
         (WebGL2): composite with the naive layers"
    )]
    NoStorageBuffers,
    #[error("reading back from the GPU failed: {0}")]
    Readback(String),
}

/// A single-mip 2D texture in [`IMAGE_FORMAT`] (the headless target's, and what the
/// window's adaptive pictures are drawn into).
pub fn image_texture(
    device: &wgpu::Device,
    label: &str,
    width: u32,
    height: u32,
    usage: wgpu::TextureUsages,
) -> wgpu::Texture {
    device.create_texture(&wgpu::TextureDescriptor {
        label: Some(label),
        size: wgpu::Extent3d {
            width,
            height,
            depth_or_array_layers: 1,
        },
        mip_level_count: 1,
        sample_count: 1,
        dimension: wgpu::TextureDimension::D2,
        format: IMAGE_FORMAT,
        usage,
        view_formats: &[],
    })
}

/// Command buffers handed to the GPU by this process, counted so a test can see that
/// an idle window submits nothing (every submission of the viewer goes through
/// [`submit`]).
static SUBMISSIONS: std::sync::atomic::AtomicU64 = std::sync::atomic::AtomicU64::new(0);

/// Submits `buffers` to `queue` and counts the submission.
pub fn submit<I>(queue: &wgpu::Queue, buffers: I) -> wgpu::SubmissionIndex
where
    I: IntoIterator<Item = wgpu::CommandBuffer>,
{
    SUBMISSIONS.fetch_add(1, std::sync::atomic::Ordering::Relaxed);
    queue.submit(buffers)
}

/// The submissions made so far (see [`submit`]).
pub fn submissions() -> u64 {
    SUBMISSIONS.load(std::sync::atomic::Ordering::Relaxed)
}

/// The format a window or canvas is drawn in: a linear (not sRGB) one where offered,
/// since the passes write display values themselves; else the first. `None`: the
/// surface offers none.
pub fn surface_format(caps: &wgpu::SurfaceCapabilities) -> Option<wgpu::TextureFormat> {
    caps.formats
        .iter()
        .copied()
        .find(|f| !f.is_srgb())
        .or_else(|| caps.formats.first().copied())
}

/// A device and queue with the adapter they came from.
#[derive(Debug, Clone)]
pub struct GpuContext {
    pub instance: wgpu::Instance,
    pub adapter: wgpu::Adapter,
    pub device: wgpu::Device,
    pub queue: wgpu::Queue,
}

impl GpuContext {
    /// A device without a window. Fails (never falls back silently) when no adapter
    /// exists.
    pub fn headless() -> Result<Self, GpuError> {
        let instance =
            wgpu::Instance::new(wgpu::InstanceDescriptor::new_without_display_handle_from_env());
        Self::with_instance(instance, None)
    }

    /// A device that can present to `surface` (made from `instance`).
    pub fn with_instance(
        instance: wgpu::Instance,
        surface: Option<&wgpu::Surface<'_>>,
    ) -> Result<Self, GpuError> {
        pollster::block_on(Self::request(instance, surface))
    }

    /// [`Self::with_instance`] without blocking: the browser, where nothing may block,
    /// awaits it.
    pub async fn request(
        instance: wgpu::Instance,
        surface: Option<&wgpu::Surface<'_>>,
    ) -> Result<Self, GpuError> {
        let adapter = instance
            .request_adapter(&wgpu::RequestAdapterOptions {
                power_preference: wgpu::PowerPreference::HighPerformance,
                force_fallback_adapter: false,
                compatible_surface: surface,
                apply_limit_buckets: false,
            })
            .await
            .map_err(|e| GpuError::NoAdapter(e.to_string()))?;
        let info = adapter.get_info();
        let (device, queue) = adapter
            .request_device(&wgpu::DeviceDescriptor {
                label: Some("texel-viewer"),
                // Optional: without them the k-buffer merges whole rectangles.
                required_features: adapter.features() & MARK_FEATURES,
                // The k-buffer and naive layers can be large: take what the adapter offers.
                required_limits: adapter.limits(),
                ..Default::default()
            })
            .await
            .map_err(|e| GpuError::Device {
                adapter: format!("{} ({:?})", info.name, info.backend),
                message: e.to_string(),
            })?;
        Ok(Self {
            instance,
            adapter,
            device,
            queue,
        })
    }

    /// "name (backend)" of the adapter.
    pub fn adapter_name(&self) -> String {
        let info = self.adapter.get_info();
        format!("{} ({:?})", info.name, info.backend)
    }

    /// Blocks until the GPU has finished all submitted work.
    pub fn wait_idle(&self) -> Result<(), GpuError> {
        self.device
            .poll(wgpu::PollType::wait_indefinitely())
            .map(|_| ())
            .map_err(|e| GpuError::Readback(e.to_string()))
    }
}
