// The CPU operators of the one walk's backward: torch_ao_kernels::walk_record and walk_backward (walk_grad.h's
// record_block and grad_block for the horizon accumulators of horizon.h, SIMD or scalar lanes, rows over torch's
// threads, each thread scattering into its own tap images) and soft_backward (soft.h's SoftAdjoint over the same
// walk: value lanes with the pixel and its slices in dual lanes (tangents 0..6), each step's d / d delta
// scattered to its taps as walk_grad.h's scatter_taps does) and exact_backward (the exact union's adjoint:
// walk_grad.h's exact_grad_block).
#include <ATen/Parallel.h>
#include <ATen/core/Tensor.h>
#include <ATen/ops/empty.h>
#include <ATen/ops/select.h>
#include <ATen/ops/zeros.h>
#include <ATen/ops/zeros_like.h>
#include <torch/library.h>

#include <algorithm>
#include <atomic>
#include <limits>
#include <string>
#include <tuple>
#include <vector>

#include "lanes_simd.h"
#include "frame_cpu.h"
#include "rows_cpu.h"
#include "walk_grad.h"

namespace {

using namespace tao;

void check_input(const at::Tensor& x, const char* name) {
  TORCH_CHECK(x.scalar_type() == at::kFloat && x.is_contiguous() && x.device().is_cpu(), name,
              ": expected contiguous float32 on the CPU");
}

// Where a backward's gradients go: the pixels' own (positions, normals, depth, the accumulator's setting)
// and the taps' (per thread)
struct Gradients {
  at::Tensor positions, normals, depth, setting, tap_positions, tap_inverse, tap_layer, tap_normals, tap_light;
  at::Tensor camera;  // (B, H, W, 4) where the intrinsics' gradients are asked for, else undefined
  int settings;       // setting's values per pixel: (B, H, W, settings)

  // input: the walk's positions (B, H, W, 3); cfg: a bilinear fetch of the depth scatters to its taps' inverse depths,
  // one of a position buffer (Sample::position_taps) and a nearest one to their positions; settings: the setting's
  // values per pixel; layer: the thickness layer's taps too; light: the senders' normals and light at the taps too;
  // camera: the intrinsics' per pixel too. The own gradients are left unset: each block zeroes its pixels'
  // (zero_own) before it adds into them, while they are in the cache.
  Gradients(const at::Tensor& input, int64_t B, int64_t H, int64_t W, const WalkSettings& cfg, int n_settings = 1,
            bool layer = false, bool light = false, bool with_camera = false)
      : settings(n_settings), bilinear(cfg.bilinear && cfg.unprojected),
        read_positions(cfg.bilinear && !cfg.unprojected ? input.data_ptr<float>() : nullptr),
        read_edge_aware(cfg.edge_aware) {
    const at::Tensor& like = input;
    const int64_t threads = at::get_num_threads();
    positions = at::empty({B, H, W, 3}, like.options()), normals = at::empty({B, H, W, 3}, like.options());
    depth = at::empty({B, H, W}, like.options()), setting = at::empty({B, H, W, settings}, like.options());
    if (with_camera) camera = at::empty({B, H, W, 4}, like.options());
    tap_positions = at::zeros({bilinear ? 0 : threads, B, H, W, 3}, like.options());
    tap_inverse = at::zeros({bilinear ? threads : 1, B, H, W}, like.options());
    if (layer) tap_layer = at::zeros({threads, B, H, W}, like.options());
    if (light) {
      tap_normals = at::zeros({threads, B, H, W, 3}, like.options());
      tap_light = at::zeros({threads, B, H, W, 3}, like.options());
    }
    has_layer = layer, has_light = light;
  }
  Targets targets(int64_t b, int64_t B, int64_t plane, int64_t thread) {
    return Targets{positions.data_ptr<float>() + 3 * b * plane, normals.data_ptr<float>() + 3 * b * plane,
                   depth.data_ptr<float>() + b * plane, setting.data_ptr<float>() + settings * b * plane,
                   bilinear ? nullptr : tap_positions.data_ptr<float>() + (thread * B + b) * 3 * plane,
                   bilinear ? tap_inverse.data_ptr<float>() + (thread * B + b) * plane : nullptr,
                   has_layer ? tap_layer.data_ptr<float>() + (thread * B + b) * plane : nullptr,
                   has_light ? tap_normals.data_ptr<float>() + (thread * B + b) * 3 * plane : nullptr,
                   has_light ? tap_light.data_ptr<float>() + (thread * B + b) * 3 * plane : nullptr,
                   camera.defined() ? camera.data_ptr<float>() + 4 * b * plane : nullptr, settings,
                   read_positions ? read_positions + 3 * b * plane : nullptr, read_edge_aware};
  }
  // zeros into the own gradients of the pixels [u_begin, u_end) of a row of image b
  void zero_own(int64_t b, int64_t row, int64_t u_begin, int64_t u_end) {
    const int64_t first = (b * positions.size(1) + row) * positions.size(2) + u_begin, n = u_end - u_begin;
    std::fill_n(positions.data_ptr<float>() + 3 * first, 3 * n, 0.0f);
    std::fill_n(normals.data_ptr<float>() + 3 * first, 3 * n, 0.0f);
    std::fill_n(depth.data_ptr<float>() + first, n, 0.0f);
    std::fill_n(setting.data_ptr<float>() + settings * first, settings * n, 0.0f);
    if (camera.defined()) std::fill_n(camera.data_ptr<float>() + 4 * first, 4 * n, 0.0f);
  }
  // the threads' tap images summed: the taps' positions into the pixels' own; the inverse depth's image (and
  // the layer's: layer())
  at::Tensor reduce() {
    float *pos = positions.data_ptr<float>(), *tp = tap_positions.data_ptr<float>();
    const int64_t threads = tap_positions.size(0), n_pos = positions.numel();
    for (int64_t k = 1; k < threads; ++k)
      for (int64_t q = 0; q < n_pos; ++q) tp[q] += tp[k * n_pos + q];
    if (threads > 0)
      for (int64_t q = 0; q < n_pos; ++q) pos[q] += tp[q];
    if (has_layer) sum_threads(tap_layer);
    if (has_light) {  // the senders' normals into the pixels' own; the light's image
      const at::Tensor senders = sum_threads(tap_normals);
      const float* sn = senders.data_ptr<float>();
      float* nrm = normals.data_ptr<float>();
      for (int64_t q = 0; q < n_pos; ++q) nrm[q] += sn[q];
      sum_threads(tap_light);
    }
    return sum_threads(tap_inverse);
  }
  // d L / d the thickness layer (B, H, W): zeros where none was read
  at::Tensor layer() const { return has_layer ? tap_layer[0] : at::zeros_like(depth); }
  // d L / d the light (B, H, W, 3): zeros where no light was read
  at::Tensor light() const { return has_light ? tap_light[0] : at::zeros_like(positions); }

 private:
  bool bilinear, has_layer = false, has_light = false;
  const float* read_positions;  // the position buffer a bilinear fetch read (Targets::read_positions), else null
  bool read_edge_aware;
  // a per-thread image (threads, B, H, W) summed into its first
  static at::Tensor sum_threads(const at::Tensor& images) {
    float* x = images.data_ptr<float>();
    const int64_t n = images[0].numel();
    for (int64_t k = 1; k < images.size(0); ++k)
      for (int64_t q = 0; q < n; ++q) x[q] += x[k * n + q];
    return images[0];
  }
};

// A backward's packed settings: n_ints and n_floats of the accumulator's after the walk's, then the walk's table
void check_settings(const at::Tensor& ints, const at::Tensor& floats, int64_t n_ints, int64_t n_floats,
                    const char* name) {
  check_input(floats, "floats");
  TORCH_CHECK(ints.scalar_type() == at::kLong && ints.is_contiguous() && ints.numel() == kAccInts + n_ints &&
                  floats.numel() == kAccFloats + n_floats + table_floats(ints.data_ptr<int64_t>()),
              "ints, floats: expected ", name, "'s packed settings");
}

// The upstream gradient: (B, C, H, W) of positions' B, H, W
void check_grad(const at::Tensor& grad, const at::Tensor& positions, int C) {
  check_input(grad, "grad");
  const int64_t B = positions.size(0), H = positions.size(1), W = positions.size(2);
  TORCH_CHECK(grad.dim() == 4 && grad.size(0) == B && grad.size(1) == C && grad.size(2) == H && grad.size(3) == W,
              "grad: expected (B, ", C, ", H, W)");
}

// The walk of every row's blocks (SIMD or scalar lanes) with the Takes visitor: the outputs (B, C, H, W), as
// the walk's, and the record (B, H, W, take_words) of every pixel's takes
template <class Acc>
void record_frame(const WalkSettings& cfg, const Acc& acc, const Frame& fr, float* dst, int64_t* record, bool scalar) {
  constexpr int L = LaneTraits<Vec>::L;
  const int64_t H = fr.H, W = fr.W, words = take_words(cfg);
  const int C = acc.channels();
  torch_ao_rows::for_each_block<L>(fr.B, H, W, scalar, [&](int64_t b, int64_t row, int64_t u0, int n, auto simd) {
    using Lane = std::conditional_t<decltype(simd)::value, Vec, float>;
    constexpr int LL = LaneTraits<Lane>::L;
    Lane values[8];
    uint64_t* pixels = reinterpret_cast<uint64_t*>(record) + ((b * H + row) * W + u0) * words;
    record_block(cfg, fr.image(b), acc, row, u0, n, pixels, values);
    alignas(64) float lanes[LL];
    for (int c = 0; c < C; ++c) {
      to_lanes(values[c], lanes);
      std::copy(lanes, lanes + n, dst + ((b * C + c) * H + row) * W + u0);
    }
  });
}

// The columns of a strip's row (kStrip pixels from u_begin) that took a step, per slice s: cols[s kStrip + i] for
// i < count[s], in order
struct StripTakes {
  std::vector<int64_t> cols;
  std::vector<int> count;
  int64_t u_begin = 0;

  // those of a record's row of image W wide, [u_begin, u_end)
  void read(const WalkSettings& cfg, const int64_t* record, int64_t W, int64_t row, int64_t begin, int64_t end) {
    cols.resize(size_t(cfg.slices * torch_ao_rows::kStrip));
    count.assign(size_t(cfg.slices), 0);
    u_begin = begin;
    for (int64_t u = begin; u < end; ++u) {
      const int64_t p = row * W + u;
      if (!took_steps(cfg, record, p)) continue;
      for (int64_t s = 0; s < cfg.slices; ++s) {  // (written in any case, counted where it took: no branch)
        cols[size_t(s * torch_ao_rows::kStrip + count[s])] = u;
        count[s] += took_steps(cfg, record, p, s) ? 1 : 0;
      }
    }
  }
  const int64_t* of(int64_t s) const { return cols.data() + s * torch_ao_rows::kStrip; }

  // Whether gathering them, slice by slice, replays fewer nodes than their blocks of L lanes, every slice of a
  // block that took any: a gathered block replays its pixels once a slice, a block once; a slice's replay (its
  // geometry and its takes) counts about three times a pixel's (HBAO: a pixel 32 nodes, a slice 55 and 28 a take)
  template <int L> bool gathering_pays() const {
    static_assert(torch_ao_rows::kStrip / L <= 64, "a strip's blocks as the bits of one word");
    constexpr int64_t kSliceCost = 3;
    uint64_t blocks = 0;
    int64_t block_slices = 0, groups = 0;
    for (size_t s = 0; s < count.size(); ++s) {
      uint64_t in_slice = 0;
      for (int i = 0; i < count[s]; ++i) in_slice |= uint64_t(1) << ((of(int64_t(s))[i] - u_begin) / L);
      block_slices += __builtin_popcountll(in_slice), blocks |= in_slice;
      groups += (count[s] + L - 1) / L;
    }
    return groups * (1 + kSliceCost) < __builtin_popcountll(blocks) + block_slices * kSliceCost;
  }
};

// A thread's scratch for the replays in lanes Lane: the recorded takes' steps, the replayed fetches, the tape
template <class Lane> struct ReplayScratch {
  std::vector<float> take_steps;
  std::vector<TapedTake<Lane>> taken;
  std::vector<Lane> partials, adjoints;
  std::vector<int32_t> parents;
  Tape<Lane> tape{nullptr, nullptr, nullptr, 0};

  // this thread's, for steps per side, fetches a slice and a tape of capacity nodes (its tape emptied)
  static ReplayScratch& of_thread(int64_t steps, int32_t fetches, int32_t capacity) {
    thread_local ReplayScratch s;
    s.take_steps.resize(size_t(2 * steps * LaneTraits<Lane>::L));
    s.taken.resize(size_t(fetches));
    s.partials.resize(size_t(Tape<Lane>::partials_size(capacity)));
    s.adjoints.resize(size_t(Tape<Lane>::adjoints_size(capacity)));
    s.parents.resize(size_t(Tape<Lane>::parents_size(capacity)));
    s.tape = Tape<Lane>(s.partials.data(), s.parents.data(), s.adjoints.data(), capacity);
    return s;
  }
};

// The gradients of every row's blocks: SIMD or scalar lanes, the forward's record of the takes, each thread's
// scratch for `fetches` fetches a slice and a tape of tape_capacity(fetches) nodes (false: a block's tape
// overflowed, its gradients unwritten). Where a slice
// without takes adds a constant (untaken_slice_constant: HBAO, PSSAO), few of a strip's pixels may have taken
// steps in a slice: the SIMD lanes then gather them, slice by slice (gathering_pays), instead of replaying every
// slice of the blocks that hold them. Each strip row zeroes its pixels' own gradients first.
template <class Acc>
bool grad_frame(const WalkSettings& cfg, const Acc& acc, const Frame& fr, const float* gp, int C, const int64_t* record,
                int32_t fetches, Gradients& out, bool scalar) {
  constexpr int L = LaneTraits<Vec>::L;
  const int64_t B = fr.B, plane = fr.H * fr.W;
  const int64_t per_image = RecordsTakes<Acc>::value ? plane * take_words(cfg) : 0;
  const int32_t capacity = tape_capacity(fetches);
  bool gathers = false;
  if constexpr (RecordsTakes<Acc>::value) gathers = !scalar && acc.untaken_slice_constant();
  std::atomic<bool> overflow{false};
  torch_ao_rows::for_each_strip_row(B, fr.H, fr.W, [&](int64_t b, int64_t row, int64_t u_begin, int64_t u_end) {
    out.zero_own(b, row, u_begin, u_end);
    const Image img = fr.image(b);
    const Targets t = out.targets(b, B, plane, at::get_thread_num());
    const int64_t* rec = record + b * per_image;
    const float* upstream[8];
    for (int c = 0; c < C; ++c) upstream[c] = gp + (b * C + c) * plane;
    // (the row's replays in lanes of lane's type, each of the lanes' pixels or a gathered block's slice `only`)
    const auto replays = [&](auto lane, const auto& each) {
      using Lane = decltype(lane);
      ReplayScratch<Lane>& s = ReplayScratch<Lane>::of_thread(cfg.steps, fetches, capacity);
      each([&](const RowLanes& lanes, int64_t only) {
        grad_lanes<Lane>(cfg, img, acc, lanes, only, upstream, C, rec, t, s.take_steps.data(), s.taken.data(),
                         fetches, s.tape);
      });
      if (s.tape.overflow) overflow = true;
    };
    if (scalar) {
      replays(0.0f, [&](const auto& replay) {
        for (int64_t u = u_begin; u < u_end; ++u) replay(RowLanes{row, u, 1}, -1);
      });
      return;
    }
    thread_local StripTakes took;
    if (gathers) took.read(cfg, rec, fr.W, row, u_begin, u_end);
    replays(Vec(0.0f), [&](const auto& replay) {
      if (gathers && took.gathering_pays<L>()) {
        for (int64_t s = 0; s < cfg.slices; ++s) {
          const int64_t* cols = took.of(s);
          for (int g = 0; g < took.count[s]; g += L)
            replay(RowLanes{row, cols[g], std::min(L, took.count[s] - g), cols + g}, s);
        }
      } else {
        for (int64_t u0 = u_begin; u0 < u_end; u0 += L)
          replay(RowLanes{row, u0, int(std::min<int64_t>(L, u_end - u0))}, -1);
      }
    });
  });
  return !overflow;
}

// The accumulator `name` of walk_backward ("gtao", "hbao", "pssao": their takes recorded by walk_record; "wedge":
// every step replayed) of the packed settings (checked), to fn
template <class Fn> void with_replayed(const std::string& name, const at::Tensor& ints, const at::Tensor& floats,
                                       const Fn& fn) {
  const int64_t* i = ints.data_ptr<int64_t>();
  const float* f = floats.data_ptr<float>();
  if (name == "gtao") {
    check_settings(ints, floats, 3, 3, "gtao");
    TORCH_CHECK(i[kAccInts] >= 0 && i[kAccInts] <= 2, "variant: expected 0 (exact), 1 (hdrp) or 2 (ue4)");
    fn(unpack_gtao(i, f));
  } else if (name == "hbao") {
    check_settings(ints, floats, 3, 2, "hbao");
    fn(unpack_hbao(i, f));
  } else if (name == "wedge") {
    check_settings(ints, floats, 1, 3, "wedge");
    TORCH_CHECK(i[3] == int64_t(Steps::wedge) && f[kAccFloats] > 0, "wedge: expected the wedge step placement and "
                "fade_distance > 0");
    fn(unpack_wedge(i, f));
  } else if (name == "pssao") {
    check_settings(ints, floats, 0, 1, "pssao");
    TORCH_CHECK(i[3] == int64_t(Steps::pixels), "pssao: expected the pixel-offset step placement");
    fn(unpack_pssao(i, f));
  } else if (name == "hemisphere") {
    check_settings(ints, floats, 0, 2, "hemisphere");
    TORCH_CHECK(i[3] == int64_t(Steps::hemisphere) && i[0] == 1 && i[7], "hemisphere: expected the hemisphere step "
                "placement over one slice, one side");
    fn(unpack_hemisphere(i, f));
  } else {
    TORCH_CHECK(false, "accumulator: the walk's backward covers gtao, hbao, wedge, pssao and hemisphere, got ", name);
  }
}

// The edge-aware fetch reads the cell flags (walk.h's Image::cells)
void check_cells(const WalkSettings& cfg, const Frame& fr) {
  TORCH_CHECK(!cfg.edge_aware || fr.cells, "cells: the edge-aware fetch needs the cell flags (B, H, W)");
}

// torch_ao_kernels::walk_record: the walk (torch_ao_kernels::walk's outputs (B, channels, H, W)) of an
// accumulator that records its takes ("gtao", "hbao", "pssao": walk_grad.h's RecordsTakes), and the record of its
// takes (B, H, W, words) int64 (words: walk_grad.h's take_words, which the caller states, as the shape of its
// fake kernel), for walk_backward
std::tuple<at::Tensor, at::Tensor> walk_record(c10::string_view accumulator, const at::Tensor& positions,
                                               const at::Tensor& normals, const at::Tensor& inverse_depth,
                                               const at::Tensor& depth, const at::Tensor& valid,
                                               const at::Tensor& intrinsics, const at::Tensor& cells,
                                               const at::Tensor& ints, const at::Tensor& floats, int64_t channels,
                                               int64_t words, bool scalar) {
  const std::string name(accumulator);
  at::Tensor out, record;
  with_replayed(name, ints, floats, [&](const auto& acc) {
    constexpr bool records = RecordsTakes<std::decay_t<decltype(acc)>>::value;
    TORCH_CHECK(records, "accumulator: ", name, " replays every step of its walk and records no takes");
    const WalkSettings cfg = unpack_walk(ints.data_ptr<int64_t>(), floats.data_ptr<float>());
    const at::Tensor none = at::empty({0}, positions.options());
    Frame fr = frame_of(positions, normals, inverse_depth, depth, valid, intrinsics, none, cells, none);
    check_cells(cfg, fr);
    const at::Tensor texels = fetch_texels(cfg, fr);
    TORCH_CHECK(acc.channels() == channels, "channels: expected ", acc.channels());
    TORCH_CHECK(words == take_words(cfg), "words: expected ", take_words(cfg), " (take_words), got ", words);
    out = at::empty({fr.B, channels, fr.H, fr.W}, positions.options());
    record = at::empty({fr.B, fr.H, fr.W, take_words(cfg)}, ints.options());
    if constexpr (records) record_frame(cfg, acc, fr, out.data_ptr<float>(), record.data_ptr<int64_t>(), scalar);
  });
  return {out, record};
}

// torch_ao_kernels::walk_backward: the gradients of sum(grad * walk(...)) with respect to the walk's
// positions, normals (B, H, W, 3), inverse depth and depth (B, H, W), and per pixel with respect to the
// accumulator's settings (B, H, W, settings: its settings(), which the caller states), and with camera with respect to the intrinsics fx, fy, cx, cy (B, H, W, 4; else
// empty); grad (B, C, H, W); accumulator "gtao", "hbao", "wedge" or "pssao" with walk()'s packed settings; cells:
// the edge-aware fetch's cell flags (B, H, W), else empty; record: walk_record's of the same call (gtao, hbao,
// pssao), else empty (every step is replayed); fetches: the most a slice replays, at least replayed_fetches' (the
// host's choice, which also picks the CUDA backward: its scratch is sized by it)
std::tuple<at::Tensor, at::Tensor, at::Tensor, at::Tensor, at::Tensor, at::Tensor> walk_backward(
    c10::string_view accumulator, const at::Tensor& grad, const at::Tensor& positions, const at::Tensor& normals,
    const at::Tensor& inverse_depth, const at::Tensor& depth, const at::Tensor& valid, const at::Tensor& intrinsics,
    const at::Tensor& cells, const at::Tensor& ints, const at::Tensor& floats, const at::Tensor& record,
    int64_t fetches, int64_t settings, bool camera, bool scalar) {
  const std::string name(accumulator);
  const at::Tensor none = at::empty({0}, positions.options());
  std::tuple<at::Tensor, at::Tensor, at::Tensor, at::Tensor, at::Tensor, at::Tensor> result;
  with_replayed(name, ints, floats, [&](const auto& acc) {
    const WalkSettings cfg = unpack_walk(ints.data_ptr<int64_t>(), floats.data_ptr<float>());
    Frame fr = frame_of(positions, normals, inverse_depth, depth, valid, intrinsics, none, cells, none);
    check_cells(cfg, fr);
    const at::Tensor texels = fetch_texels(cfg, fr);
    if constexpr (RecordsTakes<std::decay_t<decltype(acc)>>::value) {
      TORCH_CHECK(record.scalar_type() == at::kLong && record.is_contiguous() &&
                      record.sizes() == at::IntArrayRef({fr.B, fr.H, fr.W, take_words(cfg)}),
                  "record: expected walk_record's (B, H, W, words) of the same call");
    } else {
      TORCH_CHECK(record.numel() == 0, "record: ", name, " replays every step: expected an empty record");
    }
    check_grad(grad, positions, acc.channels());
    TORCH_CHECK(settings == acc.settings(), "settings: ", name, " has ", acc.settings(), ", got ", settings);
    Gradients out(positions, fr.B, fr.H, fr.W, cfg, acc.settings(), false, false, camera);
    TORCH_CHECK(fetches >= replayed_fetches(acc, cfg), "fetches: ", name, " with these settings replays up to ",
                replayed_fetches(acc, cfg), " fetches a slice (walk_grad.h's replayed_fetches), got ", fetches);
    TORCH_CHECK(grad_frame(cfg, acc, fr, grad.data_ptr<float>(), acc.channels(), record.data_ptr<int64_t>(),
                           int32_t(fetches), out, scalar),
                "walk_backward: a block's tape outgrew walk_grad.h's tape_capacity(", fetches, ")");
    const at::Tensor g_inv = out.reduce();
    result = {out.positions, out.normals, g_inv, out.depth, out.setting, camera ? out.camera : none};
  });
  return result;
}

// Whether packed settings place their steps as the GLSL shader does (the "ssilvb_glsl" variant's accumulators)
inline bool packs_glsl(const at::Tensor& ints) {
  return ints.scalar_type() == at::kLong && ints.is_contiguous() && ints.numel() >= kAccInts &&
         packed_placement(ints.data_ptr<int64_t>()) == Steps::glsl;
}

// A per-pixel walk's backward call (soft_backward, exact_backward, hard_backward): its frame, and its packed
// settings checked (n_ints, n_floats of the accumulator's; the power step placement on one half circle, at most
// max_steps per side) and unpacked
struct BackwardCall {
  Frame fr;
  at::Tensor texels;  // (what fr's bilinear fetch reads at its taps: fetch_texels)
  const int64_t* i;
  const float* f;
  WalkSettings cfg;

  BackwardCall(const at::Tensor& positions, const at::Tensor& normals, const at::Tensor& inverse_depth,
               const at::Tensor& depth, const at::Tensor& valid, const at::Tensor& intrinsics, const at::Tensor& light,
               const at::Tensor& cells, const at::Tensor& backface, const at::Tensor& ints, const at::Tensor& floats,
               int64_t n_ints, int64_t n_floats, const char* name, int64_t max_steps, bool glsl = false)
      : fr(frame_of(positions, normals, inverse_depth, depth, valid, intrinsics, light, cells, backface)) {
    check_settings(ints, floats, n_ints, n_floats, name);
    i = ints.data_ptr<int64_t>(), f = floats.data_ptr<float>();
    cfg = unpack_walk(i, f);
    check_cells(cfg, fr);
    texels = fetch_texels(cfg, fr);
    TORCH_CHECK(cfg.steps <= max_steps, "steps: the ", name, " backward holds at most ", max_steps, " per side");
    if (glsl) {  // (the shader's texels: no derivative of their own)
      TORCH_CHECK(cfg.placement == Steps::glsl && cfg.full_circle && !cfg.bilinear, name,
                  "'s backward: the GLSL step placement, nearest fetch");
    } else {
      TORCH_CHECK(cfg.placement == Steps::power && !cfg.full_circle, name,
                  "'s backward: the power step placement, one half circle");
    }
  }

  // block(lane, b, image b, row, u0, n, upstream of the image (its C channels), targets) over every row's blocks
  // (SIMD or scalar lanes: lane is a value of the lane type), then the threads' tap images reduced: (positions,
  // normals, inverse depth, depth, last) with last the setting's or the layer's image; grad (B, C, H, W)
  template <class Block>
  std::tuple<at::Tensor, at::Tensor, at::Tensor, at::Tensor, at::Tensor> run(const at::Tensor& grad, int C, bool scalar,
                                                                             Gradients& out, bool layer,
                                                                             const Block& block) const {
    check_grad(grad, out.positions, C);
    const int64_t B = fr.B, plane = fr.H * fr.W;
    const float* gp = grad.data_ptr<float>();
    torch_ao_rows::for_each_block<LaneTraits<Vec>::L>(B, fr.H, fr.W, scalar, [&](int64_t b, int64_t row, int64_t u0,
                                                                                  int n, auto simd) {
      using Lane = std::conditional_t<decltype(simd)::value, Vec, float>;
      out.zero_own(b, row, u0, u0 + n);
      block(Lane(0.0f), b, fr.image(b), row, u0, n, gp + b * C * plane, out.targets(b, B, plane, at::get_thread_num()));
    });
    at::Tensor g_inv = out.reduce();
    return {out.positions, out.normals, g_inv, out.depth, layer ? out.layer() : out.setting};
  }
};

// torch_ao_kernels::soft_backward: the gradients of sum(grad * outputs) of the soft / straight-through walk
// ("soft"'s packed settings, or with the GLSL step placement "soft_glsl"'s; its outputs the visibility, then with
// indirect light its light, with bent normals their sum) with respect to its positions, normals (B, H, W, 3; the senders' too), inverse depth and depth
// (B, H, W), each pixel's share of the thickness' offset, scale and growth (B, H, W, 3), the thickness layer (B, H, W; zeros
// where the model reads none), the light (B, H, W, 3; zeros without indirect light) and, with camera, each pixel's
// share of the intrinsics' (B, H, W, 4; else empty); grad (B, outputs, H, W); light: the light buffer, cells: the
// edge-aware fetch's cell flags (B, H, W), backface: the thickness layer (B, H, W), each empty where unused
std::tuple<at::Tensor, at::Tensor, at::Tensor, at::Tensor, at::Tensor, at::Tensor, at::Tensor, at::Tensor> soft_backward(
    const at::Tensor& grad, const at::Tensor& positions, const at::Tensor& normals, const at::Tensor& inverse_depth,
    const at::Tensor& depth, const at::Tensor& valid, const at::Tensor& intrinsics, const at::Tensor& light,
    const at::Tensor& cells, const at::Tensor& backface, const at::Tensor& ints, const at::Tensor& floats, bool camera,
    bool scalar) {
  const at::Tensor none = at::empty({0}, positions.options());
  const bool glsl = packs_glsl(ints);
  const BackwardCall call(positions, normals, inverse_depth, depth, valid, intrinsics, light, cells, backface, ints,
                          floats, glsl ? 6 : 10, glsl ? 4 : 5, glsl ? "glsl soft" : "soft", glsl ? kSoftMaxSteps : kSoftMaxSteps / 2,
                          glsl);
  TORCH_CHECK(call.f[kAccFloats + (glsl ? 3 : 2)] > 0, "tau: expected > 0");
  // (the accumulator's thickness model and whether it sends light)
  auto backward = [&](const auto& acc, const ThicknessModel& thickness, bool indirect) {
    TORCH_CHECK(!thickness.reads_layer() || call.fr.backface, "backface: the thickness model reads a layer (B, H, W)");
    TORCH_CHECK(!indirect || call.fr.light, "light: indirect light needs the light buffer (B, H, W, 3)");
    // (d L / d the thickness' offset, scale and growth)
    Gradients out(positions, call.fr.B, call.fr.H, call.fr.W, call.cfg, 3, thickness.reads_layer(), indirect,
                  camera);
    auto g = call.run(grad, acc.channels(), scalar, out, true, [&](auto lane, int64_t, const Image& img, int64_t row,
                                                                   int64_t u0, int n, const float* upstream,
                                                                   const Targets& t) {
      soft_grad_block<decltype(lane)>(call.cfg, img, acc, row, u0, n, upstream, t);
    });
    return std::tuple<at::Tensor, at::Tensor, at::Tensor, at::Tensor, at::Tensor, at::Tensor, at::Tensor, at::Tensor>{
        std::get<0>(g), std::get<1>(g), std::get<2>(g), std::get<3>(g), out.setting, std::get<4>(g), out.light(),
        camera ? out.camera : none};
  };
  if (glsl) {  // (the shader's texels are floored: no intrinsics gradient of its own)
    TORCH_CHECK(!camera, "camera: the glsl soft walk has no intrinsics gradient of its own (its positions carry them)");
    TORCH_CHECK(call.cfg.slices <= kGlslMaxSlices, "slices: the glsl soft backward holds at most ", kGlslMaxSlices - 1,
                " (sliceCount)");
    const GlslSoftAccumulator<SoftAccumulator<true, true>> acc =
        unpack_soft_glsl<SoftAccumulator<true, true>>(call.i, call.f);
    return backward(acc, acc.shader.thickness, acc.shader.indirect);
  }
  const SoftAccumulator<true, true> acc = unpack_soft<true, true>(call.i, call.f);
  return backward(acc, acc.thickness, acc.indirect);
}

// torch_ao_kernels::exact_backward: the gradients of sum(grad * visibility) of the exact union's walk ("exact"'s
// packed settings: walk_grad.h's exact_grad_block) with respect to its positions, normals (B, H, W, 3), inverse
// depth, depth and the thickness layer (B, H, W; zeros where the model reads none) and, with camera, each pixel's
// share of the intrinsics' (B, H, W, 4; else empty); grad (B, 1, H, W); cells: the edge-aware fetch's cell flags,
// backface: the thickness layer (B, H, W), each empty where unused
std::tuple<at::Tensor, at::Tensor, at::Tensor, at::Tensor, at::Tensor, at::Tensor> exact_backward(
    const at::Tensor& grad, const at::Tensor& positions, const at::Tensor& normals, const at::Tensor& inverse_depth,
    const at::Tensor& depth, const at::Tensor& valid, const at::Tensor& intrinsics, const at::Tensor& cells,
    const at::Tensor& backface, const at::Tensor& ints, const at::Tensor& floats, bool camera, bool scalar) {
  const BackwardCall call(positions, normals, inverse_depth, depth, valid, intrinsics,
                          at::empty({0}, positions.options()), cells, backface, ints, floats, 5, 5, "exact",
                          kMaxIntervals / 2);
  const ExactAccumulator acc = unpack_exact(call.i, call.f);
  TORCH_CHECK(!acc.thickness.reads_layer() || call.fr.backface, "backface: the thickness model reads a layer (B, H, W)");
  Gradients out(positions, call.fr.B, call.fr.H, call.fr.W, call.cfg, 1, acc.thickness.reads_layer(), false,
                camera);
  const at::Tensor none = at::empty({0}, positions.options());
  auto g = call.run(grad, 1, scalar, out, true, [&](auto lane, int64_t, const Image& img, int64_t row, int64_t u0,
                                                    int n, const float* upstream, const Targets& t) {
    exact_grad_block<decltype(lane)>(call.cfg, img, acc, row, u0, n, upstream, t);
  });
  return {std::get<0>(g), std::get<1>(g), std::get<2>(g), std::get<3>(g), std::get<4>(g), camera ? out.camera : none};
}

// The images a hard sector walk reads beyond the G-buffer: the light (indirect light), the thickness' layer
inline void check_hard_inputs(const BackwardCall& call, bool indirect, const ThicknessModel& thickness) {
  TORCH_CHECK(!indirect || call.fr.light, "light: indirect light reads a light image (B, H, W, 3)");
  TORCH_CHECK(!thickness.reads_layer() || call.fr.backface, "backface: the thickness model reads a layer (B, H, W)");
}

// The hard sector walk's call (hard_record, hard_backward): "bitmask"'s packed settings (with indirect light, its
// light image), or, with the GLSL step placement, "glsl"'s (the "ssilvb_glsl" variant's; its backward: indirect
// light's); fn(call, acc) with the accumulator unpacked
template <class Fn>
auto with_hard_accumulator(const at::Tensor& positions, const at::Tensor& normals, const at::Tensor& inverse_depth,
                           const at::Tensor& depth, const at::Tensor& valid, const at::Tensor& intrinsics,
                           const at::Tensor& light, const at::Tensor& cells, const at::Tensor& backface,
                           const at::Tensor& ints, const at::Tensor& floats, const Fn& fn) {
  const bool glsl = packs_glsl(ints);
  const BackwardCall call(positions, normals, inverse_depth, depth, valid, intrinsics, light, cells, backface, ints,
                          floats, glsl ? 4 : 8, glsl ? 3 : 5, glsl ? "glsl hard" : "hard",
                          std::numeric_limits<int64_t>::max(), glsl);
  if (glsl) {
    const GlslAccumulator acc = unpack_glsl(call.i, call.f);
    check_hard_inputs(call, acc.indirect, acc.thickness);
    return fn(call, acc);
  }
  const BitmaskAccumulator acc = unpack_bitmask(call.i, call.f);
  check_hard_inputs(call, acc.indirect, acc.thickness);
  return fn(call, acc);
}

// torch_ao_kernels::hard_record: the hard sector walk (torch_ao_kernels::walk's "bitmask" or "glsl" outputs (B,
// channels, H, W)) and the record of each pixel's slices' occupied sectors (B, H, W, slices) int32, for
// hard_backward (channels and slices as the settings say: the shapes of the outputs)
std::tuple<at::Tensor, at::Tensor> hard_record(const at::Tensor& positions, const at::Tensor& normals,
                                               const at::Tensor& inverse_depth, const at::Tensor& depth,
                                               const at::Tensor& valid, const at::Tensor& intrinsics,
                                               const at::Tensor& light, const at::Tensor& cells,
                                               const at::Tensor& backface, const at::Tensor& ints,
                                               const at::Tensor& floats, int64_t channels, int64_t slices,
                                               bool scalar) {
  return with_hard_accumulator(positions, normals, inverse_depth, depth, valid, intrinsics, light, cells, backface,
                               ints, floats, [&](const BackwardCall& call, const auto& acc) {
    TORCH_CHECK(acc.channels() == channels, "channels: expected ", acc.channels());
    TORCH_CHECK(call.cfg.slices == slices, "slices: expected the settings' ", call.cfg.slices);
    const int64_t B = call.fr.B, H = call.fr.H, W = call.fr.W;
    at::Tensor out = at::empty({B, channels, H, W}, positions.options());
    at::Tensor record = at::empty({B, H, W, call.cfg.slices}, positions.options().dtype(at::kInt));
    float* dst = out.data_ptr<float>();
    int32_t* rec = record.data_ptr<int32_t>();
    torch_ao_rows::for_each_block<LaneTraits<Vec>::L>(B, H, W, scalar, [&](int64_t b, int64_t row, int64_t u0, int n,
                                                                         auto simd) {
      using Lane = std::conditional_t<decltype(simd)::value, Vec, float>;
      constexpr int LL = LaneTraits<Lane>::L;
      Lane values[8];
      hard_record_block(call.cfg, call.fr.image(b), acc, row, u0, n, rec + b * H * W * call.cfg.slices, values);
      alignas(64) float lanes[LL];
      for (int c = 0; c < channels; ++c) {
        to_lanes(values[c], lanes);
        std::copy(lanes, lanes + n, dst + ((b * channels + c) * H + row) * W + u0);
      }
    });
    return std::tuple<at::Tensor, at::Tensor>{out, record};
  });
}

// torch_ao_kernels::hard_backward: the gradients of sum(grad * outputs) of the hard sector walk (walk_grad.h's
// hard_grad_block) with respect to its positions, normals (B, H, W, 3), inverse depth and depth (B, H, W), and
// the light (B, H, W, 3; zeros without indirect light) and, with camera, each pixel's share of the intrinsics'
// (B, H, W, 4; else empty: indirect light's, the rest reads them through the positions alone; the "glsl"
// accumulator's texels do not move: none); grad (B, C, H, W); record: hard_record's of the same call
std::tuple<at::Tensor, at::Tensor, at::Tensor, at::Tensor, at::Tensor, at::Tensor> hard_backward(
    const at::Tensor& grad, const at::Tensor& positions, const at::Tensor& normals, const at::Tensor& inverse_depth,
    const at::Tensor& depth, const at::Tensor& valid, const at::Tensor& intrinsics, const at::Tensor& light,
    const at::Tensor& cells, const at::Tensor& backface, const at::Tensor& ints, const at::Tensor& floats,
    const at::Tensor& record, bool camera, bool scalar) {
  return with_hard_accumulator(positions, normals, inverse_depth, depth, valid, intrinsics, light, cells, backface,
                               ints, floats, [&](const BackwardCall& call, const auto& acc) {
    TORCH_CHECK(record.scalar_type() == at::kInt && record.is_contiguous() &&
                    record.sizes() == at::IntArrayRef({call.fr.B, call.fr.H, call.fr.W, call.cfg.slices}),
                "record: expected hard_record's (B, H, W, slices) of the same call");
    const int32_t* rec = record.data_ptr<int32_t>();
    const int64_t per_image = call.fr.H * call.fr.W * call.cfg.slices;
    Gradients out(positions, call.fr.B, call.fr.H, call.fr.W, call.cfg, 1, false, acc.indirect, camera);
    const auto g = call.run(grad, acc.channels(), scalar, out, false, [&](auto lane, int64_t b, const Image& img,
                                                                        int64_t row, int64_t u0, int n,
                                                                        const float* upstream, const Targets& t) {
      hard_grad_block<decltype(lane)>(call.cfg, img, acc, row, u0, n, upstream, rec + b * per_image, t);
    });
    return std::tuple<at::Tensor, at::Tensor, at::Tensor, at::Tensor, at::Tensor, at::Tensor>{
        std::get<0>(g), std::get<1>(g), std::get<2>(g), std::get<3>(g), out.light(),
        camera ? out.camera : at::empty({0}, positions.options())};
  });
}

}  // namespace

TORCH_LIBRARY_FRAGMENT(torch_ao_kernels, m) {
  m.def("walk_record(str accumulator, Tensor positions, Tensor normals, Tensor inverse_depth, Tensor depth, "
        "Tensor valid, Tensor intrinsics, Tensor cells, Tensor ints, Tensor floats, int channels, int words, "
        "bool scalar) "
        "-> (Tensor, Tensor)");
  m.impl("walk_record", c10::DispatchKey::CPU, TORCH_FN(walk_record));
  m.def("walk_backward(str accumulator, Tensor grad, Tensor positions, Tensor normals, Tensor inverse_depth, "
        "Tensor depth, Tensor valid, Tensor intrinsics, Tensor cells, Tensor ints, Tensor floats, Tensor record, "
        "int fetches, int settings, bool camera, bool scalar) "
        "-> (Tensor, Tensor, Tensor, Tensor, Tensor, Tensor)");
  m.impl("walk_backward", c10::DispatchKey::CPU, TORCH_FN(walk_backward));
  m.def("soft_backward(Tensor grad, Tensor positions, Tensor normals, Tensor inverse_depth, Tensor depth, "
        "Tensor valid, Tensor intrinsics, Tensor light, Tensor cells, Tensor backface, Tensor ints, Tensor floats, "
        "bool camera, bool scalar) -> (Tensor, Tensor, Tensor, Tensor, Tensor, Tensor, Tensor, Tensor)");
  m.impl("soft_backward", c10::DispatchKey::CPU, TORCH_FN(soft_backward));
  m.def("exact_backward(Tensor grad, Tensor positions, Tensor normals, Tensor inverse_depth, Tensor depth, "
        "Tensor valid, Tensor intrinsics, Tensor cells, Tensor backface, Tensor ints, Tensor floats, bool camera, "
        "bool scalar) -> (Tensor, Tensor, Tensor, Tensor, Tensor, Tensor)");
  m.impl("exact_backward", c10::DispatchKey::CPU, TORCH_FN(exact_backward));
  m.def("hard_record(Tensor positions, Tensor normals, Tensor inverse_depth, Tensor depth, Tensor valid, "
        "Tensor intrinsics, Tensor light, Tensor cells, Tensor backface, Tensor ints, Tensor floats, int channels, "
        "int slices, bool scalar) -> (Tensor, Tensor)");
  m.impl("hard_record", c10::DispatchKey::CPU, TORCH_FN(hard_record));
  m.def("hard_backward(Tensor grad, Tensor positions, Tensor normals, Tensor inverse_depth, Tensor depth, "
        "Tensor valid, Tensor intrinsics, Tensor light, Tensor cells, Tensor backface, Tensor ints, Tensor floats, "
        "Tensor record, bool camera, bool scalar) -> (Tensor, Tensor, Tensor, Tensor, Tensor, Tensor)");
  m.impl("hard_backward", c10::DispatchKey::CPU, TORCH_FN(hard_backward));
}
