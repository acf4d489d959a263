// The CUDA kernels of the one walk: one thread per pixel in float lanes (lanes_scalar.h), compiled at run
// time by NVRTC (torch_ao/kernels/launch.py inlines the headers ahead of this file). Each thread runs
// walk_pixel, which the CPU's scalar lanes run too (tests/test_kernels*.py, lanes="scalar").
#include "packed.h"
#include "walk_grad.h"

// The entries come in groups, each between `#if !defined(TAO_ONE_GROUP) || defined(TAO_GROUP_<NAME>)` and its
// `#endif`: a CUDA call compiles its entry's group alone at the group's first use (launch.py's cuda_groups; a
// forward-only user compiles the walks, seconds, not every backward, minutes), and without TAO_ONE_GROUP every
// group compiles (the tests, cuda_offline.py)

// (bounds: the kernel's __launch_bounds__, or nothing)
#define TAO_CUDA_ENTRY(name, unpack, bounds)                                                                \
  extern "C" __global__ void bounds name(const float* positions, const float* normals, const float* inverse,     \
                                  const float* depth, const bool* valid, const float* intrinsics,        \
                                  const float* light, const float* cells, const float* backface, float* out, \
                                  const int64_t* ints, const float* floats, int B, int H, int W) {        \
    const int64_t p = int64_t(blockIdx.x) * blockDim.x + threadIdx.x;                                    \
    if (p >= int64_t(B) * H * W) return;                                                                  \
    const tao::Frame frame{positions, normals, inverse, depth, intrinsics, light, cells, backface, valid, B, H, W}; \
    tao::walk_pixel(tao::unpack_walk(ints, floats), tao::unpack(ints, floats), frame, out, p);            \
  }

#if !defined(TAO_ONE_GROUP) || defined(TAO_GROUP_WALKS)
TAO_CUDA_ENTRY(tao_walk_gtao, unpack_gtao, )
TAO_CUDA_ENTRY(tao_walk_hbao, unpack_hbao, )
// (3 blocks of launch.py's 128 threads a multiprocessor, at most 170 registers a thread: the thickness growth's
// sample distance would take the compiler to 186, and 2 blocks)
TAO_CUDA_ENTRY(tao_walk_bitmask, unpack_bitmask, __launch_bounds__(128, 3))
TAO_CUDA_ENTRY(tao_walk_exact, unpack_exact, __launch_bounds__(128, 4))
TAO_CUDA_ENTRY(tao_walk_exact_gradients, unpack_exact_gradients_plain, )  // d visibility / d radius, thickness, scale too
TAO_CUDA_ENTRY(tao_walk_exact_gradients_growth, unpack_exact_gradients_growth, )  // ... and d growth
TAO_CUDA_ENTRY(tao_walk_glsl, unpack_glsl, )
TAO_CUDA_ENTRY(tao_walk_wedge, unpack_wedge, )
TAO_CUDA_ENTRY(tao_walk_pssao, unpack_pssao, )
TAO_CUDA_ENTRY(tao_walk_hemisphere, unpack_hemisphere, )
TAO_CUDA_ENTRY(tao_walk_soft, unpack_soft_forward, )
TAO_CUDA_ENTRY(tao_walk_soft_gradients, unpack_soft_gradients, )  // d visibility / d radius, offset, scale too
// the same where a slice's steps fit 16 (every preset's): its thread's steps' arrays a quarter as long (3.6 kB of local
// memory a thread against 11.3 kB), as tao_soft_backward_short below
TAO_CUDA_ENTRY(tao_walk_soft_gradients_short, unpack_soft_gradients_short, )
TAO_CUDA_ENTRY(tao_walk_soft_glsl, unpack_soft_glsl_forward, )  // the "ssilvb_glsl" variant's (soft_glsl.h)
#endif

// The horizon accumulators' backward (walk_grad.h): the forward with its record of the takes, then the replay,
// the pixel's own gradients written by its thread and its taps' scattered atomically; the CPU's scalar lanes
// run the same record_block and grad_block. A backward's thread keeps a tape for `fetches` replayed fetches a
// slice in local memory, which the driver reserves for every thread the GPU holds at once (an H100's 270,336):
// 107 kB a thread for 32 steps a side, 29 GB of device memory. So each accumulator has the entries its calls
// need (walk_grad.py's cuda_backward picks one): _small, 4 fetches a slice (where a take replaces the state: each
// side's last one alone; or 4 steps on one side, as HBAO's default 3), _short, 16 (8 steps a side, 16 where a
// slice has one: every preset's), and the full 2 kGradMaxSteps
#define TAO_CUDA_RECORD(name, unpack)                                                                       \
  extern "C" __global__ void name(const float* positions, const float* normals, const float* inverse,     \
                                  const float* depth, const bool* valid, const float* intrinsics,        \
                                  const float* cells, float* out, int64_t* record, const int64_t* ints,   \
                                  const float* floats, int B, int H, int W) {                            \
    const int64_t p = int64_t(blockIdx.x) * blockDim.x + threadIdx.x;                                    \
    if (p >= int64_t(B) * H * W) return;                                                                  \
    const tao::Frame frame{positions, normals, inverse, depth, intrinsics, nullptr, cells, nullptr, valid, B, H, W}; \
    tao::record_pixel(tao::unpack_walk(ints, floats), tao::unpack(ints, floats), frame, out, record, p);  \
  }
#define TAO_CUDA_BACKWARD(name, unpack, fetches)                                                            \
  extern "C" __global__ void name(const float* positions, const float* normals, const float* inverse,     \
                                  const float* depth, const bool* valid, const float* intrinsics,        \
                                  const float* cells, const float* grad, const int64_t* record,           \
                                  float* g_positions, float* g_normals, float* g_depth, float* g_setting, \
                                  float* tap_positions, float* tap_inverse, float* g_camera,              \
                                  const int64_t* ints, const float* floats, int B, int H, int W) {        \
    const int64_t p = int64_t(blockIdx.x) * blockDim.x + threadIdx.x;                                    \
    if (p >= int64_t(B) * H * W) return;                                                                  \
    const tao::Frame frame{positions, normals, inverse, depth, intrinsics, nullptr, cells, nullptr, valid, B, H, W}; \
    tao::grad_pixel<decltype(tao::unpack(ints, floats)), fetches>(                                      \
        tao::unpack_walk(ints, floats), tao::unpack(ints, floats), frame, grad, record, g_positions, g_normals, \
        g_depth, g_setting, tap_positions, tap_inverse, g_camera, p);                                    \
  }

constexpr int kFetchesAll = 2 * tao::kGradMaxSteps, kFetchesShort = 16, kFetchesSmall = 4;
#if !defined(TAO_ONE_GROUP) || defined(TAO_GROUP_RECORDS)
TAO_CUDA_RECORD(tao_record_gtao, unpack_gtao)
TAO_CUDA_RECORD(tao_record_hbao, unpack_hbao)
TAO_CUDA_RECORD(tao_record_pssao, unpack_pssao)
#endif
// (each backward of GTAO and of HBAO a group of its own: a call compiles the one it runs)
#if !defined(TAO_ONE_GROUP) || defined(TAO_GROUP_GTAO_SMALL)
TAO_CUDA_BACKWARD(tao_backward_gtao_small, unpack_gtao, kFetchesSmall)  // (the exact variant's)
#endif
#if !defined(TAO_ONE_GROUP) || defined(TAO_GROUP_GTAO_SHORT)
TAO_CUDA_BACKWARD(tao_backward_gtao_short, unpack_gtao, kFetchesShort)
#endif
#if !defined(TAO_ONE_GROUP) || defined(TAO_GROUP_GTAO)
TAO_CUDA_BACKWARD(tao_backward_gtao, unpack_gtao, kFetchesAll)
#endif
#if !defined(TAO_ONE_GROUP) || defined(TAO_GROUP_HBAO_SMALL)
TAO_CUDA_BACKWARD(tao_backward_hbao_small, unpack_hbao, kFetchesSmall)  // (accumulate="max", or 4 steps)
#endif
#if !defined(TAO_ONE_GROUP) || defined(TAO_GROUP_HBAO_SHORT)
TAO_CUDA_BACKWARD(tao_backward_hbao_short, unpack_hbao, kFetchesShort)
#endif
#if !defined(TAO_ONE_GROUP) || defined(TAO_GROUP_HBAO)
TAO_CUDA_BACKWARD(tao_backward_hbao, unpack_hbao, kFetchesAll)
#endif
#if !defined(TAO_ONE_GROUP) || defined(TAO_GROUP_SSAO)
TAO_CUDA_BACKWARD(tao_backward_wedge, unpack_wedge, kFetchesAll)  // (every step replayed: no record)
TAO_CUDA_BACKWARD(tao_backward_wedge_short, unpack_wedge, kFetchesShort)
TAO_CUDA_BACKWARD(tao_backward_pssao_small, unpack_pssao, kFetchesSmall)  // (always: its highest sample)
TAO_CUDA_BACKWARD(tao_backward_hemisphere, unpack_hemisphere, kFetchesAll)
TAO_CUDA_BACKWARD(tao_backward_hemisphere_short, unpack_hemisphere, kFetchesShort)
#endif

// The soft / straight-through bitmask walk's backward (walk_grad.h's soft_grad_block): d L / d the thickness'
// offset, scale and growth per pixel in g_thickness (B, H, W, 3); the layer's taps' in tap_layer (backface: the model's
// layer); with indirect light the senders' normals' and light's taps' in tap_normals and tap_light (light: the
// light buffer); d L / d the intrinsics per pixel in g_camera (B, H, W, 4) where it is not null
#define TAO_CUDA_SOFT_BACKWARD(name, Acc, unpack)                                                            \
  extern "C" __global__ void name(const float* positions, const float* normals, const float* inverse,          \
                                  const float* depth, const bool* valid, const float* intrinsics,             \
                                  const float* light, const float* cells, const float* backface,              \
                                  const float* grad, float* g_positions, float* g_normals, float* g_depth,    \
                                  float* g_thickness, float* tap_positions, float* tap_inverse,               \
                                  float* tap_layer, float* tap_normals, float* tap_light, float* g_camera,    \
                                  const int64_t* ints, const float* floats, int B, int H, int W) {            \
    const int64_t p = int64_t(blockIdx.x) * blockDim.x + threadIdx.x;                                         \
    if (p >= int64_t(B) * H * W) return;                                                                       \
    const tao::Frame frame{positions, normals, inverse, depth, intrinsics, light, cells, backface, valid, B, H, W}; \
    const Acc acc = unpack(ints, floats);                                                                      \
    const tao::ThicknessModel& thickness = tao::soft_thickness(acc);                                          \
    const bool indirect = tao::soft_indirect(acc);                                                            \
    tao::soft_grad_pixel(tao::unpack_walk(ints, floats), acc, frame, grad, g_positions, g_normals, g_depth,   \
                         g_thickness, tap_positions, tap_inverse, thickness.reads_layer() ? tap_layer : nullptr, \
                         indirect ? tap_normals : nullptr, indirect ? tap_light : nullptr, g_camera, p);  \
  }

#if !defined(TAO_ONE_GROUP) || defined(TAO_GROUP_SOFT)
using SoftBackward = tao::SoftAccumulator<true, true>;
using SoftBackwardShort = tao::SoftAccumulator<true, true, tao::kSoftShortSteps>;
TAO_CUDA_SOFT_BACKWARD(tao_soft_backward, SoftBackward, (tao::unpack_soft<true, true>))
// a slice of at most 16 steps (8 a side: every preset's), whose kept steps take a quarter of the local memory:
// 57x faster at 1920x1080 (3 x 3) on an H200, where the thread's 85 kB of local memory is what it waits on
TAO_CUDA_SOFT_BACKWARD(tao_soft_backward_short, SoftBackwardShort, (tao::unpack_soft<true, true, tao::kSoftShortSteps>))
// the "ssilvb_glsl" variant's (g_camera null: its texels are floored), up to 64 and 16 steps a slice
using GlslSoftBackward = tao::GlslSoftAccumulator<SoftBackward>;
using GlslSoftBackwardShort = tao::GlslSoftAccumulator<SoftBackwardShort>;
TAO_CUDA_SOFT_BACKWARD(tao_soft_backward_glsl, GlslSoftBackward, tao::unpack_soft_glsl<SoftBackward>)
TAO_CUDA_SOFT_BACKWARD(tao_soft_backward_glsl_short, GlslSoftBackwardShort, tao::unpack_soft_glsl<SoftBackwardShort>)
#endif

// The exact union's backward (walk_grad.h's exact_grad_block): the pixel's own gradients (d L / d the intrinsics in
// g_camera where it is not null), its intervals' taps' (positions, inverse depth, the thickness layer's where the
// model reads one) atomically
#if !defined(TAO_ONE_GROUP) || defined(TAO_GROUP_EXACT)
extern "C" __global__ void tao_exact_backward(const float* positions, const float* normals, const float* inverse,
                                              const float* depth, const bool* valid, const float* intrinsics,
                                              const float* cells, const float* backface, const float* grad,
                                              float* g_positions, float* g_normals, float* g_depth,
                                              float* tap_positions, float* tap_inverse, float* tap_layer,
                                              float* g_camera, const int64_t* ints, const float* floats, int B, int H,
                                              int W) {
  const int64_t p = int64_t(blockIdx.x) * blockDim.x + threadIdx.x;
  if (p >= int64_t(B) * H * W) return;
  const tao::Frame frame{positions, normals, inverse, depth, intrinsics, nullptr, cells, backface, valid, B, H, W};
  const tao::ExactAccumulator acc = tao::unpack_exact(ints, floats);
  tao::exact_grad_pixel(tao::unpack_walk(ints, floats), acc, frame, grad, g_positions, g_normals, g_depth,
                        tap_positions, tap_inverse, acc.thickness.reads_layer() ? tap_layer : nullptr, g_camera, p);
}
#endif

// The hard sector walk's forward with its record, and its backward (walk_grad.h's hard_record_block,
// hard_grad_block): the pixel's own gradients (cosine weights, bent normals, indirect light) and, with indirect
// light, its steps' taps' (atomically); of the "bitmask" accumulator (tao_record_hard, tao_hard_backward) and of
// the "ssilvb_glsl" variant's (bitmask_glsl.h's GlslAccumulator: its record the mask it carries after each slice,
// its backward indirect light's: the pixel's own normal and position, the taps' positions, normals and light)
#define TAO_CUDA_HARD(record_name, backward_name, unpack, bounds)                                                   \
  extern "C" __global__ void bounds record_name(const float* positions, const float* normals, const float* inverse, \
                                         const float* depth, const bool* valid, const float* intrinsics,            \
                                         const float* light, const float* cells, const float* backface,             \
                                         float* out, int32_t* record, const int64_t* ints, const float* floats,     \
                                         int B, int H, int W) {                                                     \
    const int64_t p = int64_t(blockIdx.x) * blockDim.x + threadIdx.x;                                               \
    if (p >= int64_t(B) * H * W) return;                                                                            \
    const tao::Frame frame{positions, normals, inverse, depth, intrinsics, light, cells, backface, valid, B, H, W}; \
    tao::hard_record_pixel(tao::unpack_walk(ints, floats), tao::unpack(ints, floats), frame, out, record, p);       \
  }                                                                                                                 \
  extern "C" __global__ void backward_name(const float* positions, const float* normals, const float* inverse,      \
                                           const float* depth, const bool* valid, const float* intrinsics,          \
                                           const float* light, const float* cells, const float* backface,           \
                                           const float* grad, const int32_t* record, float* g_positions,            \
                                           float* g_normals, float* g_depth, float* tap_positions,                  \
                                           float* tap_inverse, float* tap_normals, float* tap_light,                \
                                           float* g_camera, const int64_t* ints, const float* floats, int B,        \
                                           int H, int W) {                                                          \
    const int64_t p = int64_t(blockIdx.x) * blockDim.x + threadIdx.x;                                               \
    if (p >= int64_t(B) * H * W) return;                                                                            \
    const tao::Frame frame{positions, normals, inverse, depth, intrinsics, light, cells, backface, valid, B, H, W}; \
    tao::hard_grad_pixel(tao::unpack_walk(ints, floats), tao::unpack(ints, floats), frame, grad, record,            \
                         g_positions, g_normals, g_depth, tap_positions, tap_inverse, tap_normals, tap_light,       \
                         g_camera, p);                                                                              \
  }

// (the record's bounds: tao_walk_bitmask's, the same walk)
#if !defined(TAO_ONE_GROUP) || defined(TAO_GROUP_HARD)
TAO_CUDA_HARD(tao_record_hard, tao_hard_backward, unpack_bitmask, __launch_bounds__(128, 3))
TAO_CUDA_HARD(tao_record_hard_glsl, tao_hard_backward_glsl, unpack_glsl, )
#endif
