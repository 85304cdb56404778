//! rtstream inside an engine's frame, on lavapipe with validation and synchronization
//! validation on:
//! - the engine creates its instance and device with plain ash (below, `Engine`), hands them to
//!   rtstream (`VulkanContext::from_external`), and records rtstream's frame work (the manager's
//!   builds, refits and TLAS, then the renderer's three passes) into its own command buffers,
//!   three frames in flight, one submission per frame, never waiting on the frame path;
//! - a frame held back on the GPU (its submission waits on a timeline value the host signals
//!   later) keeps everything it references alive and unwritten while the manager runs three more
//!   frames;
//! - a device without what rtstream needs is a typed error naming what is missing.
//!
//! The `unsafe` here is the engine's side: creating and driving its own Vulkan objects.
//!
//! Why one file over 600 lines: about half of it is the test's own minimal engine (`Engine`:
//! instance, device, frames in flight, timeline semaphore, written with plain ash), which no other
//! test uses; the three scenarios need it next to them to show what an engine does around rtstream.

mod common;

use std::ffi::{c_void, CString};
use std::sync::{Arc, Mutex};

use ash::{ext, khr, vk};
use glam::Vec3;
use rtstream::as_manager::backend::vulkan::{
    ash, DeviceFeatures, ExternalDevice, FrameCmd, TlasRef, VulkanBackendDesc, VulkanContext,
    VulkanError, REQUIRED_DEVICE_EXTENSIONS,
};
use rtstream::as_manager::backend::{BackendError, TlasHandle};
use rtstream::as_manager::{AsError, FrameInput, Viewpoint};
use rtstream::renderer::{Camera, RenderDesc, Renderer};

/// Validation warnings and errors the engine's messenger received.
static MESSAGES: Mutex<Vec<String>> = Mutex::new(Vec::new());

/// Records every message: the messenger is made for validation and performance warnings and
/// errors only.
unsafe extern "system" fn on_message(
    _severity: vk::DebugUtilsMessageSeverityFlagsEXT,
    _types: vk::DebugUtilsMessageTypeFlagsEXT,
    data: *const vk::DebugUtilsMessengerCallbackDataEXT<'_>,
    _user: *mut c_void,
) -> vk::Bool32 {
    // SAFETY: the loader passes valid callback data for the call's duration, and a non-null
    // p_message is NUL-terminated.
    let text = unsafe { data.as_ref().and_then(|d| d.message_as_c_str()) }
        .map(|m| m.to_string_lossy().into_owned())
        .unwrap_or_default();
    MESSAGES.lock().unwrap().push(text);
    vk::FALSE
}

/// What the engine enables; `ray_query: false` makes a device rtstream must refuse.
struct EngineSetup {
    ray_query: bool,
    acceleration_structure: bool,
}

/// An engine's Vulkan objects, made as an engine would make them.
struct Engine {
    _entry: ash::Entry,
    instance: ash::Instance,
    debug: ext::debug_utils::Instance,
    messenger: vk::DebugUtilsMessengerEXT,
    physical_device: vk::PhysicalDevice,
    device: ash::Device,
    family: u32,
    queue: vk::Queue,
    pool: vk::CommandPool,
    cmds: Vec<vk::CommandBuffer>,
    /// Frame `n`'s submission signals `n + 1`.
    timeline: vk::Semaphore,
    /// A gate the host opens (signals 1) to let a held-back submission run.
    gate: vk::Semaphore,
    extensions: Vec<CString>,
    features: DeviceFeatures,
}

fn timeline_semaphore(device: &ash::Device) -> vk::Semaphore {
    let mut ty = vk::SemaphoreTypeCreateInfo::default()
        .semaphore_type(vk::SemaphoreType::TIMELINE)
        .initial_value(0);
    // SAFETY: valid device and create-info.
    unsafe { device.create_semaphore(&vk::SemaphoreCreateInfo::default().push_next(&mut ty), None) }
        .expect("timeline semaphore")
}

impl Engine {
    fn new(setup: EngineSetup, frames_in_flight: u32) -> Engine {
        MESSAGES.lock().unwrap().clear();
        // SAFETY: loading the system's Vulkan loader.
        let entry = unsafe { ash::Entry::load() }.expect("Vulkan loader");
        let app = vk::ApplicationInfo::default()
            .application_name(c"engine")
            .api_version(vk::API_VERSION_1_3);
        let layers = [c"VK_LAYER_KHRONOS_validation".as_ptr()];
        let exts = [ext::debug_utils::NAME.as_ptr()];
        let enables = [vk::ValidationFeatureEnableEXT::SYNCHRONIZATION_VALIDATION];
        let mut features =
            vk::ValidationFeaturesEXT::default().enabled_validation_features(&enables);
        let info = vk::InstanceCreateInfo::default()
            .application_info(&app)
            .enabled_layer_names(&layers)
            .enabled_extension_names(&exts)
            .push_next(&mut features);
        // SAFETY: every pointer in `info` outlives the call.
        let instance = unsafe { entry.create_instance(&info, None) }
            .expect("instance with the validation layer (scripts/setup.sh installs it)");
        let debug = ext::debug_utils::Instance::new(&entry, &instance);
        let messenger_info = vk::DebugUtilsMessengerCreateInfoEXT::default()
            .message_severity(
                vk::DebugUtilsMessageSeverityFlagsEXT::WARNING
                    | vk::DebugUtilsMessageSeverityFlagsEXT::ERROR,
            )
            .message_type(
                vk::DebugUtilsMessageTypeFlagsEXT::VALIDATION
                    | vk::DebugUtilsMessageTypeFlagsEXT::PERFORMANCE,
            )
            .pfn_user_callback(Some(on_message));
        // SAFETY: valid instance; the callback is a plain function.
        let messenger = unsafe { debug.create_debug_utils_messenger(&messenger_info, None) }
            .expect("messenger");
        // The first device with ray queries (lavapipe here).
        // SAFETY: valid instance.
        let physical_device = unsafe { instance.enumerate_physical_devices() }
            .expect("devices")
            .into_iter()
            .find(|&pd| {
                // SAFETY: pd belongs to the instance.
                unsafe { instance.enumerate_device_extension_properties(pd) }
                    .unwrap_or_default()
                    .iter()
                    .any(|e| e.extension_name_as_c_str() == Ok(khr::ray_query::NAME))
            })
            .expect("a device with VK_KHR_ray_query (lavapipe: scripts/setup.sh)");
        // SAFETY: as above.
        let family =
            unsafe { instance.get_physical_device_queue_family_properties(physical_device) }
                .iter()
                .position(|f| f.queue_flags.contains(vk::QueueFlags::COMPUTE))
                .expect("a compute queue") as u32;
        let mut extensions: Vec<CString> = vec![khr::deferred_host_operations::NAME.to_owned()];
        if setup.acceleration_structure {
            extensions.push(khr::acceleration_structure::NAME.to_owned());
        }
        if setup.ray_query {
            extensions.push(khr::ray_query::NAME.to_owned());
        }
        let ext_ptrs: Vec<_> = extensions.iter().map(|e| e.as_ptr()).collect();
        let priorities = [1.0];
        let queues = [vk::DeviceQueueCreateInfo::default()
            .queue_family_index(family)
            .queue_priorities(&priorities)];
        let mut v12 = vk::PhysicalDeviceVulkan12Features::default()
            .buffer_device_address(true)
            .timeline_semaphore(true)
            .host_query_reset(true);
        let mut v13 = vk::PhysicalDeviceVulkan13Features::default()
            .synchronization2(true)
            .maintenance4(true);
        let mut asf = vk::PhysicalDeviceAccelerationStructureFeaturesKHR::default()
            .acceleration_structure(true);
        let mut rqf = vk::PhysicalDeviceRayQueryFeaturesKHR::default().ray_query(true);
        let mut feats = vk::PhysicalDeviceFeatures2::default()
            .features(vk::PhysicalDeviceFeatures::default().shader_int64(true))
            .push_next(&mut v12)
            .push_next(&mut v13);
        if setup.acceleration_structure {
            feats = feats.push_next(&mut asf);
        }
        if setup.ray_query {
            feats = feats.push_next(&mut rqf);
        }
        let info = vk::DeviceCreateInfo::default()
            .queue_create_infos(&queues)
            .enabled_extension_names(&ext_ptrs)
            .push_next(&mut feats);
        // SAFETY: pd belongs to the instance; every chained struct outlives the call.
        let device =
            unsafe { instance.create_device(physical_device, &info, None) }.expect("device");
        // SAFETY: family and index 0 were requested above.
        let queue = unsafe { device.get_device_queue(family, 0) };
        // SAFETY: valid device and create-info.
        let pool = unsafe {
            device.create_command_pool(
                &vk::CommandPoolCreateInfo::default()
                    .queue_family_index(family)
                    .flags(vk::CommandPoolCreateFlags::RESET_COMMAND_BUFFER),
                None,
            )
        }
        .expect("pool");
        // SAFETY: the pool was just created.
        let cmds = unsafe {
            device.allocate_command_buffers(
                &vk::CommandBufferAllocateInfo::default()
                    .command_pool(pool)
                    .level(vk::CommandBufferLevel::PRIMARY)
                    .command_buffer_count(frames_in_flight),
            )
        }
        .expect("command buffers");
        let timeline = timeline_semaphore(&device);
        let gate = timeline_semaphore(&device);
        Engine {
            _entry: entry,
            instance,
            debug,
            messenger,
            physical_device,
            device,
            family,
            queue,
            pool,
            cmds,
            timeline,
            gate,
            extensions,
            features: DeviceFeatures {
                ray_query: setup.ray_query,
                acceleration_structure: setup.acceleration_structure,
                ..DeviceFeatures::REQUIRED
            },
        }
    }

    /// What the engine hands to rtstream.
    fn handover(&self) -> ExternalDevice {
        ExternalDevice {
            instance: self.instance.clone(),
            physical_device: self.physical_device,
            device: self.device.clone(),
            queue_family: self.family,
            queue: self.queue,
            enabled_extensions: self.extensions.clone(),
            enabled_features: self.features,
            allocator: None,
            debug_utils: true,
        }
    }

    /// The latest frame whose submission completed.
    fn completed(&self) -> Option<u64> {
        // SAFETY: our own timeline.
        let v = unsafe { self.device.get_semaphore_counter_value(self.timeline) }.unwrap();
        v.checked_sub(1)
    }

    fn wait(&self, frame: u64) {
        let (s, v) = ([self.timeline], [frame + 1]);
        // SAFETY: our own timeline; the value is signalled by a submitted frame.
        unsafe {
            self.device.wait_semaphores(
                &vk::SemaphoreWaitInfo::default().semaphores(&s).values(&v),
                u64::MAX,
            )
        }
        .unwrap();
    }

    /// Begins frame `frame`'s command buffer (its previous frame was waited for).
    fn begin(&self, frame: u64) -> FrameCmd {
        let cmd = self.cmds[frame as usize % self.cmds.len()];
        // SAFETY: the command buffer's last submission completed (the caller waited).
        unsafe {
            self.device
                .reset_command_buffer(cmd, vk::CommandBufferResetFlags::empty())
                .unwrap();
            self.device
                .begin_command_buffer(
                    cmd,
                    &vk::CommandBufferBeginInfo::default()
                        .flags(vk::CommandBufferUsageFlags::ONE_TIME_SUBMIT),
                )
                .unwrap();
            // SAFETY: a primary of this device's queue family, recording, outside a render
            // pass; submitted in frame order below; `completed` is read from the timeline.
            FrameCmd::from_engine(cmd, frame, self.completed())
        }
    }

    /// Ends and submits frame `cmd` (signalling `frame + 1`); `gated` makes it wait for the host
    /// to open the gate first.
    fn submit(&self, cmd: FrameCmd, gated: bool) {
        // SAFETY: recording since `begin`.
        unsafe { self.device.end_command_buffer(cmd.raw()) }.unwrap();
        let cmds = [vk::CommandBufferSubmitInfo::default().command_buffer(cmd.raw())];
        let signal = [vk::SemaphoreSubmitInfo::default()
            .semaphore(self.timeline)
            .value(cmd.frame() + 1)
            .stage_mask(vk::PipelineStageFlags2::ALL_COMMANDS)];
        let wait = [vk::SemaphoreSubmitInfo::default()
            .semaphore(self.gate)
            .value(1)
            .stage_mask(vk::PipelineStageFlags2::ALL_COMMANDS)];
        let mut submit = vk::SubmitInfo2::default()
            .command_buffer_infos(&cmds)
            .signal_semaphore_infos(&signal);
        if gated {
            submit = submit.wait_semaphore_infos(&wait);
        }
        // SAFETY: one thread drives the queue here; every handle is valid.
        unsafe {
            self.device
                .queue_submit2(self.queue, &[submit], vk::Fence::null())
        }
        .unwrap();
    }

    fn open_gate(&self) {
        // SAFETY: our own timeline semaphore, signalled once from 0 to 1.
        unsafe {
            self.device.signal_semaphore(
                &vk::SemaphoreSignalInfo::default()
                    .semaphore(self.gate)
                    .value(1),
            )
        }
        .unwrap();
    }

    fn messages(&self) -> Vec<String> {
        MESSAGES.lock().unwrap().clone()
    }

    /// Fails the test if the engine's messenger received a validation message.
    fn assert_no_messages(&self) {
        let messages = self.messages();
        assert!(
            messages.is_empty(),
            "validation messages:\n{}",
            messages.join("\n")
        );
    }
}

/// An engine with everything rtstream needs.
fn full_engine(frames_in_flight: u32) -> Engine {
    Engine::new(
        EngineSetup {
            ray_query: true,
            acceleration_structure: true,
        },
        frames_in_flight,
    )
}

impl Drop for Engine {
    fn drop(&mut self) {
        // A held-back frame must not block the wait below (a failed test drops here).
        // SAFETY: our own semaphore.
        if unsafe { self.device.get_semaphore_counter_value(self.gate) } == Ok(0) {
            self.open_gate();
        }
        // SAFETY: the engine destroys its objects after rtstream's context dropped (the tests
        // drop it first) and after the device is idle.
        unsafe {
            let _ = self.device.device_wait_idle();
            self.device.destroy_semaphore(self.gate, None);
            self.device.destroy_semaphore(self.timeline, None);
            self.device.destroy_command_pool(self.pool, None);
            self.device.destroy_device(None);
            self.debug
                .destroy_debug_utils_messenger(self.messenger, None);
            self.instance.destroy_instance(None);
        }
    }
}

type Scene = common::GridWalk;

/// 24 static grids in two rows of 165 m along the camera's walk and a skinned cloth (refitted every frame).
fn scene(ctx: &Arc<VulkanContext>, frames_in_flight: u32) -> Scene {
    scene_with(ctx, VulkanBackendDesc::engine_recorded(frames_in_flight))
}

fn scene_with(ctx: &Arc<VulkanContext>, desc: VulkanBackendDesc) -> Scene {
    let mut c = common::lavapipe_config(40.0, 50.0);
    c.residency.release_threshold = 2;
    c.residency.min_resident_frames = 0;
    c.build.max_primitives = 3_000;
    Scene::new(ctx, desc, c, 12)
}

/// The camera of frame `frame`: along the rows at 2.5 m a frame, so BLASes are built ahead and
/// freed behind while frames are in flight; `jump` metres further along (a teleport).
fn camera(frame: u64, jump: f32) -> Viewpoint {
    Viewpoint::new(
        Vec3::new(frame as f32 * 2.5 - 10.0 + jump, 3.0, 0.0),
        Vec3::new(0.3, -0.1, 1.0),
    )
}

fn update(s: &mut Scene, frame: u64) -> Result<TlasHandle, AsError> {
    update_at(s, frame, 0.0)
}

fn update_at(s: &mut Scene, frame: u64, jump: f32) -> Result<TlasHandle, AsError> {
    s.pose(frame);
    let cams = [camera(frame, jump)];
    s.m.update(FrameInput {
        frame,
        cameras: &cams,
    })
    .map(|o| o.tlas)
}

fn render_desc(frame: u64) -> RenderDesc {
    let c = camera(frame, 0.0);
    RenderDesc::new(
        64,
        48,
        Camera::look_at(c.position, c.position + c.forward, 60f32.to_radians()),
    )
}

/// Retires the frames the engine finished and takes the rendered frames that are ready.
fn retire_completed(
    engine: &Engine,
    s: &mut Scene,
    renderer: &mut Renderer,
    images: &mut Vec<rtstream::renderer::Frame>,
) {
    if let Some(done) = engine.completed() {
        s.m.backend_mut().frame_done(done);
        while let Some(f) = renderer.take(images.len() as u64, Some(done)).unwrap() {
            images.push(f);
        }
    }
}

/// Records frame `frame`'s work into the engine's command buffer: the manager's, then the
/// renderer's passes over `tlas`.
fn record_frame(
    engine: &Engine,
    s: &mut Scene,
    renderer: &mut Renderer,
    tlas: TlasRef,
    frame: u64,
) -> FrameCmd {
    let cmd = engine.begin(frame);
    s.m.backend_mut().record(&cmd).unwrap();
    renderer
        .record(&cmd, tlas, &[], &render_desc(frame))
        .unwrap();
    cmd
}

/// The BLAS address in the cloth's TLAS instance record (customIndex 100, the low 24 bits after
/// the 3x4 transform), if the cloth is in `records`.
fn cloth_address(records: &[u8]) -> Option<u64> {
    records
        .chunks_exact(64)
        .find(|r| u32::from_le_bytes(r[48..52].try_into().unwrap()) & 0xff_ffff == 100)
        .map(|r| u64::from_le_bytes(r[56..64].try_into().unwrap()))
}

/// Three frames in flight in the engine's own command buffers, rendered, and the recorded
/// frames equal to the blocking renderer's images of the same TLAS.
#[test]
fn an_engine_device_records_rtstream_into_its_own_frames() {
    const IN_FLIGHT: u32 = 3;
    const FRAMES: u64 = 40;
    let engine = full_engine(IN_FLIGHT);
    let ctx = Arc::new(VulkanContext::from_external(engine.handover()).expect("engine device"));
    assert!(ctx.is_external());
    let mut s = scene(&ctx, IN_FLIGHT);
    let mut renderer = Renderer::new(ctx.clone()).unwrap();
    let mut images = Vec::new();
    let mut max_in_flight = 0;
    let mut last = None;
    for frame in 0..FRAMES {
        if frame >= u64::from(IN_FLIGHT) {
            engine.wait(frame - u64::from(IN_FLIGHT));
        }
        retire_completed(&engine, &mut s, &mut renderer, &mut images);
        let handle = update(&mut s, frame).unwrap();
        last = Some(handle);
        let tlas = s.m.backend().resolve_tlas(handle).unwrap();
        let cmd = record_frame(&engine, &mut s, &mut renderer, tlas, frame);
        engine.submit(cmd, false);
        max_in_flight = max_in_flight.max(frame + 1 - engine.completed().map_or(0, |c| c + 1));
    }
    engine.wait(FRAMES - 1);
    retire_completed(&engine, &mut s, &mut renderer, &mut images);
    assert_eq!(
        images.len() as u64,
        FRAMES,
        "every recorded frame reads back"
    );
    let counters = s.m.backend().counters();
    assert!(counters.built > 10 && counters.refits > 10, "{counters:?}");
    assert!(
        counters.destroyed > 0,
        "BLASes were freed behind the camera: {counters:?}"
    );
    eprintln!("engine frames: {counters:?}, at most {max_in_flight} frames in flight");
    // The manager's builds run beside its TLAS and show from the next frame: frame 0 builds,
    // and every frame after it shows the scene.
    assert!(
        counters.builds_beside_tlas > 0,
        "builds ran beside the TLAS: {counters:?}"
    );
    for (f, img) in images.iter().enumerate().skip(1) {
        assert!(img.hit_fraction() > 0.05, "frame {f} shows the scene");
        assert!(img.passes.primary_ms >= 0.0);
    }
    // The last frame again, through the blocking renderer and the same TLAS: the same image.
    let last = s.m.backend().resolve_tlas(last.unwrap()).unwrap();
    let blocking = renderer
        .render(last, &[], &render_desc(FRAMES - 1))
        .unwrap();
    let recorded = images.last().unwrap();
    let same = blocking
        .hits
        .iter()
        .zip(&recorded.hits)
        .filter(|(a, b)| a == b)
        .count();
    assert_eq!(
        same,
        blocking.hits.len(),
        "recorded and blocking frames agree"
    );
    drop(renderer);
    drop(s);
    drop(ctx);
    engine.assert_no_messages();
}

/// What frame N references: its TLAS handle, its instance records, the BLAS addresses they
/// name, and the cloth's pose buffer (address, contents).
type Held = (TlasHandle, Vec<u8>, Vec<u64>, u64, Vec<u8>);

/// Frame N's submission waits for the host; meanwhile the manager runs frames N+1 to N+3. Until
/// the host lets frame N run, nothing it references is destroyed or rewritten: its TLAS, its
/// instance records, the BLASes they name and the cloth's pose it was built from.
#[test]
fn a_frame_held_back_on_the_gpu_keeps_what_it_references() {
    const IN_FLIGHT: u32 = 4;
    let engine = full_engine(IN_FLIGHT);
    let ctx = Arc::new(VulkanContext::from_external(engine.handover()).unwrap());
    let mut s = scene(&ctx, IN_FLIGHT);
    let mut renderer = Renderer::new(ctx.clone()).unwrap();
    // Warm up: frames 0..10 as usual, then frame 10 is held back.
    let held = 10u64;
    let mut held_state: Option<Held> = None;
    for frame in 0..=held + 3 {
        if frame >= u64::from(IN_FLIGHT) {
            // Frames up to N - 1 only: N + 3 - IN_FLIGHT < N.
            engine.wait(frame - u64::from(IN_FLIGHT));
        }
        if let Some(done) = engine.completed() {
            s.m.backend_mut().frame_done(done);
        }
        // After frame N the camera jumps 100 m ahead: what frame N traces leaves r2 and is
        // freed by the manager while frame N is still held.
        let jump = if frame > held { 100.0 } else { 0.0 };
        let handle = update_at(&mut s, frame, jump).unwrap();
        let tlas = s.m.backend().resolve_tlas(handle).unwrap();
        let cmd = record_frame(&engine, &mut s, &mut renderer, tlas, frame);
        if frame == held {
            // What frame N references, before anything later runs.
            let b = s.m.backend();
            let records = b.tlas_instance_bytes(handle).expect("frame N's records");
            let addresses: Vec<u64> = records
                .chunks_exact(64)
                .map(|r| u64::from_le_bytes(r[56..64].try_into().unwrap()))
                .collect();
            assert!(addresses.len() > 5, "frame N traces a scene");
            let cloth_blas = cloth_address(&records).expect("the cloth is in frame N");
            let (pose_address, _) = b.shading_geometry(cloth_blas).unwrap();
            let pose = b.input_buffer_bytes(pose_address).unwrap();
            engine.submit(cmd, true);
            held_state = Some((handle, records, addresses, pose_address, pose));
        } else {
            engine.submit(cmd, false);
        }
        if frame > held {
            let (handle, records, addresses, pose_address, pose) = held_state.as_ref().unwrap();
            let b = s.m.backend();
            assert!(engine.completed() < Some(held), "frame N is still held");
            assert!(b.resolve_tlas(*handle).is_ok(), "frame N's TLAS is kept");
            assert_eq!(
                &b.tlas_instance_bytes(*handle).unwrap(),
                records,
                "records unwritten"
            );
            for a in addresses {
                assert!(
                    b.is_blas_address_retained(*a),
                    "a BLAS of frame N was destroyed"
                );
            }
            assert_eq!(
                &b.input_buffer_bytes(*pose_address)
                    .expect("the pose buffer exists"),
                pose,
                "frame N's cloth pose was rewritten"
            );
        }
    }
    // Some BLAS frame N uses was freed meanwhile (retiring, not destroyed): the walk moved on.
    let (handle, _, addresses, _, _) = held_state.clone().unwrap();
    assert!(
        addresses
            .iter()
            .any(|&a| !s.m.backend().is_live_blas_address(a)),
        "the test frees something frame N uses"
    );
    // A fourth frame would reuse frame N's slot: refused, typed, nothing recorded.
    match update_at(&mut s, held + 4, 100.0) {
        Err(AsError::Backend(BackendError::FrameInFlight { waiting_for, .. })) => {
            assert_eq!(waiting_for, held)
        }
        other => panic!("expected FrameInFlight, got {other:?}"),
    }
    engine.open_gate();
    engine.wait(held + 3);
    s.m.backend_mut().frame_done(held + 3);
    let img = renderer
        .take(held, engine.completed())
        .unwrap()
        .expect("frame N renders");
    assert!(img.hit_fraction() > 0.05);
    // Once done, frame N's slot is reused and its handle goes stale: an error, not a newer TLAS.
    update_at(&mut s, held + 4, 100.0).unwrap();
    let cmd = engine.begin(held + 4);
    s.m.backend_mut().record(&cmd).unwrap();
    engine.submit(cmd, false);
    engine.wait(held + 4);
    s.m.backend_mut().frame_done(held + 4);
    assert!(matches!(
        s.m.backend().resolve_tlas(handle),
        Err(VulkanError::StaleHandle { what: "TLAS", .. })
    ));
    drop(renderer);
    drop(s);
    drop(ctx);
    engine.assert_no_messages();
}

/// A device without acceleration structures or ray queries: a typed error naming each.
#[test]
fn a_device_without_what_rtstream_needs_is_a_typed_error() {
    let engine = Engine::new(
        EngineSetup {
            ray_query: false,
            acceleration_structure: false,
        },
        1,
    );
    match VulkanContext::from_external(engine.handover()) {
        Err(VulkanError::MissingDeviceSupport {
            extensions,
            features,
            ..
        }) => {
            assert!(
                extensions
                    .iter()
                    .any(|e| e == "VK_KHR_acceleration_structure"),
                "{extensions:?}"
            );
            assert!(
                extensions.iter().any(|e| e.contains("VK_KHR_ray_query")),
                "{extensions:?}"
            );
            assert!(
                features.iter().any(|f| f == "accelerationStructure"),
                "{features:?}"
            );
        }
        other => panic!("expected MissingDeviceSupport, got {other:?}"),
    }
    let _ = REQUIRED_DEVICE_EXTENSIONS;
}

/// Separate refit targets (for an engine tracing on another queue): the cloth's refits write a
/// ring of three structures, so its address cycles through three values and a frame in flight
/// never sees its structure rewritten; the images equal those of in-place refits, frame by
/// frame, and the manager's memory accounting covers the ring.
#[test]
fn separate_refit_targets_rotate_and_render_the_same() {
    const IN_FLIGHT: u32 = 3;
    const FRAMES: u64 = 16;
    let run = |separate: bool| {
        let engine = full_engine(IN_FLIGHT);
        let ctx = Arc::new(VulkanContext::from_external(engine.handover()).unwrap());
        let mut s = scene_with(
            &ctx,
            VulkanBackendDesc {
                separate_refit_targets: separate,
                ..VulkanBackendDesc::engine_recorded(IN_FLIGHT)
            },
        );
        let mut renderer = Renderer::new(ctx.clone()).unwrap();
        let (mut images, mut cloth) = (Vec::new(), Vec::new());
        for frame in 0..FRAMES {
            if frame >= u64::from(IN_FLIGHT) {
                engine.wait(frame - u64::from(IN_FLIGHT));
            }
            retire_completed(&engine, &mut s, &mut renderer, &mut images);
            let handle = update(&mut s, frame).unwrap();
            let b = s.m.backend();
            let records = b.tlas_instance_bytes(handle).unwrap();
            let address = cloth_address(&records);
            if let Some(a) = address {
                // Every cloth structure a frame still in flight may trace exists.
                let done = engine.completed();
                for (f, earlier) in cloth.iter().filter(|(f, _)| Some(*f) > done) {
                    assert!(
                        b.is_blas_address_retained(*earlier),
                        "separate {separate}, frame {frame}: {f}'s {earlier:#x} (now {a:#x}, \
                         live {}, {:?})",
                        b.is_live_blas_address(*earlier),
                        b.counters()
                    );
                }
                cloth.push((frame, a));
            }
            let tlas = b.resolve_tlas(handle).unwrap();
            let cmd = record_frame(&engine, &mut s, &mut renderer, tlas, frame);
            engine.submit(cmd, false);
        }
        engine.wait(FRAMES - 1);
        retire_completed(&engine, &mut s, &mut renderer, &mut images);
        let storage = s.m.backend().blas_storage_bytes();
        let accounted = s.m.stats().blas_bytes;
        drop(renderer);
        drop(s);
        drop(ctx);
        engine.assert_no_messages();
        (images, cloth, storage, accounted)
    };
    let (in_place, cloth_a, _, _) = run(false);
    let (ring, cloth_b, storage, accounted) = run(true);
    let distinct = |c: &[(u64, u64)]| {
        let mut v: Vec<u64> = c.iter().map(|x| x.1).collect();
        v.sort_unstable();
        v.dedup();
        v.len()
    };
    assert_eq!(distinct(&cloth_a), 1, "in place: one structure");
    assert_eq!(distinct(&cloth_b), 3, "a ring of three");
    // After the ring filled, the address repeats every three refits.
    let tail: Vec<u64> = cloth_b.iter().rev().take(6).map(|x| x.1).collect();
    assert_eq!(tail[0], tail[3]);
    assert_ne!(tail[0], tail[1]);
    assert!(
        storage <= accounted,
        "the manager counts {accounted} bytes; the backend holds {storage}"
    );
    assert_eq!(in_place.len(), ring.len());
    for (f, (a, b)) in in_place.iter().zip(&ring).enumerate() {
        assert_eq!(
            a.hits, b.hits,
            "frame {f}: ring and in-place refits render alike"
        );
    }
}
