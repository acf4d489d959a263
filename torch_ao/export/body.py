"""The shader body shared by the GLSL and HLSL exports: torch_ao's walk transcribed, one pixel at a time.

It is written once, in the subset the two languages share, with HLSL's type names (``float2``,
``float3``, ``atan2``, ``frac``); the GLSL prelude maps those onto GLSL by ``#define`` (see
:mod:`torch_ao.export`). The fitted constants arrive as ``#define`` lines (``AO_*``) and select the
branches by ``#if``. Each function names the tensor-op code it transcribes; that code is the
specification. Image coordinates are torch_ao's: ``u`` to the right, ``v`` down, row 0 at the top;
the prelude's loaders (``aoPosition``, ``aoNormal``, ``aoBackface``) read texel ``(x, y)`` so.
"""
from __future__ import annotations

__all__ = ["BODY"]

BODY = r"""
#define AO_PI 3.14159265358979
#define AO_HALF_PI 1.57079632679490

int aoWidth() { return int(aoSize().x); }
int aoHeight() { return int(aoSize().y); }

// torch.lerp: a + w (b - a) below w = 1/2, b - (b - a)(1 - w) above (the same rounding)
float aoLerp(float a, float b, float w) { return w < 0.5 ? a + w * (b - a) : b - (b - a) * (1.0 - w); }

float aoBilerp(float t0, float t1, float t2, float t3, float fu, float fv)
{
    return aoLerp(aoLerp(t0, t1, fu), aoLerp(t2, t3, fu), fv);
}

// walk/patterns.py interleaved_gradient_noise: frac(52.9829189 frac(a x + b y)) at integer pixels; the
// inner product split as frac(AH x) + AL x (AH x exact below 4096 pixels) so float32 keeps the phase.
float aoNoise(float x, float y, float phase)
{
    float inner = frac(frac(AO_NOISE_AH * x) + AO_NOISE_AL * x + frac(AO_NOISE_BH * y) + AO_NOISE_BL * y + phase);
    return frac(52.9829189 * inner);
}

// Inverse depth of a texel, 0 where it is background or outside the image (walk/fetch.py).
float aoInverseDepth(int x, int y)
{
    if (x < 0 || y < 0 || x >= aoWidth() || y >= aoHeight()) return 0.0;
    float4 p = aoPosition(x, y);
    return p.w != 0.0 ? 1.0 / (-p.z) : 0.0;
}

#if AO_FETCH == 2
// walk/fetch.py _continuous_pairs for the pair (k, k+1) along a row (alongRow) or a column: both texels
// valid, and within EDGE_MIN_RATIO, or the jump within its neighbours' range widened by EDGE_SLOPE_TOLERANCE
// of itself; a pair alone in its line, matching the parallel pair beside it.
float aoInverseAt(int ln, int k, bool alongRow) { return alongRow ? aoInverseDepth(k, ln) : aoInverseDepth(ln, k); }

bool aoPairBoth(int ln, int k, bool alongRow)
{
    return aoInverseAt(ln, k, alongRow) > 0.0 && aoInverseAt(ln, k + 1, alongRow) > 0.0;
}

float aoPairJump(int ln, int k, bool alongRow) { return aoInverseAt(ln, k + 1, alongRow) - aoInverseAt(ln, k, alongRow); }

bool aoContinuousPair(int ln, int k, bool alongRow)
{
    float a = aoInverseAt(ln, k, alongRow);
    float b = aoInverseAt(ln, k + 1, alongRow);
    if (!(a > 0.0 && b > 0.0)) return false;
    if (max(a, b) <= AO_EDGE_MIN_RATIO * min(a, b)) return true;
    float jump = b - a;
    bool hasBefore = aoPairBoth(ln, k - 1, alongRow);
    bool hasAfter = aoPairBoth(ln, k + 1, alongRow);
    float before = hasBefore ? aoPairJump(ln, k - 1, alongRow) : 0.0;
    float after = hasAfter ? aoPairJump(ln, k + 1, alongRow) : 0.0;
    float lo = hasBefore && hasAfter ? min(before, after) : (hasBefore ? before : after);
    float hi = hasBefore && hasAfter ? max(before, after) : (hasBefore ? before : after);
    float tol = AO_EDGE_SLOPE_TOLERANCE * abs(jump);
    if ((hasBefore || hasAfter) && jump >= lo - tol && jump <= hi + tol) return true;
    int lineCount = alongRow ? aoHeight() : aoWidth();
    if (lineCount > 1 && !(hasBefore || hasAfter)) {
        if (aoPairBoth(ln - 1, k, alongRow) && abs(aoPairJump(ln - 1, k, alongRow) - jump) <= tol) return true;
        if (aoPairBoth(ln + 1, k, alongRow) && abs(aoPairJump(ln + 1, k, alongRow) - jump) <= tol) return true;
    }
    return false;
}

// continuous_cell_image: the 2x2 cell whose top-left texel is (x, y) is one surface.
bool aoSmoothCell(int x, int y)
{
    return aoContinuousPair(y, x, true) && aoContinuousPair(y + 1, x, true)
        && aoContinuousPair(x, y, false) && aoContinuousPair(x + 1, y, false);
}
#endif

// The back-face layer at a texel (thickness.py BackfaceThickness.buffers): back - depth, in [0, 1e6].
float aoLayer(int x, int y)
{
#if AO_THICKNESS_MODEL == 2
    float4 p = aoPosition(x, y);
    if (p.w == 0.0) return 0.0;
    return clamp(aoBackface(x, y) - (-p.z), 0.0, AO_BACKFACE_CAP);
#else
    return 0.0;
#endif
}

struct AOSample
{
    bool valid;
    float3 position;
    float layer;
};

// walk/fetch.py Footprint.at / position and walk/sample.py fetch_sample: the sample at screen (su, sv).
AOSample aoFetch(float su, float sv, int ownX, int ownY, float4 intr)
{
    AOSample f;
    int W = aoWidth();
    int H = aoHeight();
#if AO_FETCH == 0
    int iu = int(floor(su + (0.5 - AO_NEAREST_TIE)));
    int iv = int(floor(sv + (0.5 - AO_NEAREST_TIE)));
    bool inside = iu >= 0 && iu < W && iv >= 0 && iv < H;
    int cu = clamp(iu, 0, W - 1);
    int cv = clamp(iv, 0, H - 1);
    float4 p = aoPosition(cu, cv);
    f.valid = p.w != 0.0;
    f.position = p.xyz;
    f.layer = aoLayer(cu, cv);
#else
    float u0 = floor(su);
    float v0 = floor(sv);
    float fu = su - u0;
    float fv = sv - v0;
    bool inside = u0 >= 0.0 && u0 + 1.0 < float(W) && v0 >= 0.0 && v0 + 1.0 < float(H);
    int iu0 = int(clamp(u0, -1.0, float(W)));
    int iv0 = int(clamp(v0, -1.0, float(H)));
    int c0 = clamp(iu0, 0, W - 1);
    int c1 = clamp(iu0 + 1, 0, W - 1);
    int r0 = clamp(iv0, 0, H - 1);
    int r1 = clamp(iv0 + 1, 0, H - 1);
    bool oneTap = false;
#if AO_FETCH == 2
    // edge_aware_taps: the four taps inside one surface, else four copies of the nearest one
    bool smoothCell;
    if (c1 != c0 && r1 != r0) {
        smoothCell = aoSmoothCell(c0, r0);
    } else {
        float i0 = aoInverseDepth(c0, r0);
        float i1 = aoInverseDepth(c1, r0);
        float i2 = aoInverseDepth(c0, r1);
        float i3 = aoInverseDepth(c1, r1);
        float lo = min(min(i0, i1), min(i2, i3));
        float hi = max(max(i0, i1), max(i2, i3));
        smoothCell = lo > 0.0 && hi <= AO_EDGE_MIN_RATIO * lo;
    }
    if (!smoothCell) {
        int nu = fu >= 0.5 + AO_NEAREST_TIE ? c1 : c0;
        int nv = fv >= 0.5 + AO_NEAREST_TIE ? r1 : r0;
        c0 = nu; c1 = nu; r0 = nv; r1 = nv;
        oneTap = true;
    }
#endif
    float4 p0 = aoPosition(c0, r0);
    float4 p1 = aoPosition(c1, r0);
    float4 p2 = aoPosition(c0, r1);
    float4 p3 = aoPosition(c1, r1);
    f.valid = p0.w != 0.0 && p1.w != 0.0 && p2.w != 0.0 && p3.w != 0.0;
#if AO_FETCH == 2
    if (oneTap && c0 == ownX && r0 == ownY) f.valid = false;  // Footprint.on_own_texel
#endif
    float depth = 1.0 / aoBilerp(1.0 / (-p0.z), 1.0 / (-p1.z), 1.0 / (-p2.z), 1.0 / (-p3.z), fu, fv);
    float cu = clamp(su, 0.0, float(W - 1));
    float cv = clamp(sv, 0.0, float(H - 1));
    f.position = float3((cu - intr.z) / intr.x * depth, -(cv - intr.w) / intr.y * depth, -depth);
#if AO_THICKNESS_MODEL == 2
    f.layer = aoBilerp(aoLayer(c0, r0), aoLayer(c1, r0), aoLayer(c0, r1), aoLayer(c1, r1), fu, fv);
#else
    f.layer = 0.0;
#endif
#endif
#if AO_BORDER_DROP
    f.valid = f.valid && inside;
#endif
    return f;
}

// ops.py arc_measure: H(theta) = int_0^theta cos(t - gamma) |sin t| dt
float aoArcF(float t, float gamma) { return -cos(2.0 * t - gamma) / 4.0 + t * sin(gamma) / 2.0; }
float aoArcMeasure(float theta, float gamma) { return sign(theta) * (aoArcF(theta, gamma) - aoArcF(0.0, gamma)); }

#if AO_METHOD == 1
// ---------------------------------------------------------------- bitmask AO (methods/bitmask.py)
// sectors/rule.py hard_mask: bits floor(s) .. floor(s) + count - 1 of 32, count = ceil/round/floor(w)
uint aoSectorBits(float s, float w)
{
    int start = int(clamp(floor(s), 0.0, 63.0));
#if AO_ROUNDING == 0
    float c = ceil(w);
#elif AO_ROUNDING == 1
    float c = roundEven(w);
#else
    float c = floor(w);
#endif
    int count = int(clamp(c, 0.0, 32.0));
    if (count <= 0 || start >= 32) return 0u;
    uint run = 0xFFFFFFFFu >> uint(32 - count);
    return run << uint(start);
}

int aoPopcount(uint v)
{
    v = v - ((v >> 1u) & 0x55555555u);
    v = (v & 0x33333333u) + ((v >> 2u) & 0x33333333u);
    v = (v + (v >> 4u)) & 0x0F0F0F0Fu;
    return int((v * 0x01010101u) >> 24u);
}

// methods/bitmask_common.py _cosine_measure: |n_p| (H(theta(x)) - H(theta(0))), theta(x) = gamma - pi/2 + pi x / 32
float aoCosineMeasure(float x, float gamma, float len)
{
    return (aoArcMeasure(gamma + (x * (AO_PI / 32.0) - AO_HALF_PI), gamma) - aoArcMeasure(gamma - AO_HALF_PI, gamma)) * len;
}
#endif

float aoVisibility(int px, int py)
{
    float4 p4 = aoPosition(px, py);
    if (p4.w == 0.0) return 1.0;  // background
    float3 P = p4.xyz;
    float3 N = aoNormal(px, py);
    float3 V = normalize(-P);
    float d = -P.z;
    float2 size = aoSize();
    // intrinsics (fx, fy, cx, cy) in pixels from the OpenGL projection (camera.py opengl_projection)
    float4 intr = float4(aoProjection(0, 0) * size.x / 2.0, aoProjection(1, 1) * size.y / 2.0,
                         (size.x * (1.0 - aoProjection(0, 2)) - 1.0) / 2.0, (size.y * (aoProjection(1, 2) + 1.0) - 1.0) / 2.0);
    float u = float(px);
    float v = float(py);
#if AO_JITTER
    float noiseSlice = aoNoise(u, v, AO_NOISE_PHASE_SLICE);
    float noiseStep = aoNoise(u, v, AO_NOISE_PHASE_STEP);
#else
    float noiseSlice = 0.0;
    float noiseStep = 0.5;
#endif
    float sumVis = 0.0;
    float sumDen = 0.0;
    for (int s = 0; s < AO_SLICES; s++) {
        // walk/patterns.py SlicePattern.slice_tangent
        float angle = (float(s) + noiseSlice) * (AO_PI / float(AO_SLICES));
#if AO_AZIMUTH_VIEW
        float3 e1 = cross(float3(0.0, 1.0, 0.0), V);
        e1 = e1 / max(length(e1), 1e-12);
        float3 e2 = cross(V, e1);
        float3 T = cos(angle) * e1 + sin(angle) * e2;
#else
        float3 dirScreen = float3(cos(angle), sin(angle), 0.0);
        float3 T = dirScreen - dot(dirScreen, V) * V;
        T = T / max(length(T), 1e-12);
#endif
        // walk/walk.py slice_geometry
        float3 axis = cross(T, V);
        float3 nProj = N - axis * dot(N, axis);
        float len = length(nProj);
        float gamma = atan2(dot(nProj, T), dot(nProj, V));
        float2 ppu = float2(intr.x * (T.x + P.x * T.z / d) / d, -intr.y * (T.y + P.y * T.z / d) / d);
        float2 dir = ppu / max(length(ppu), 1e-12);
#if AO_SAMPLE_EXTENT_SPHERE
        // intervals.py sphere_stretch
        float ratio = AO_RADIUS / length(P);
        ppu = ppu * rsqrt(max(1.0 - ratio * ratio, 0.01));
#endif
        float radiusPx = AO_WALK_RADIUS * length(ppu);
#ifdef AO_MAX_RADIUS_PX
        radiusPx = min(radiusPx, AO_MAX_RADIUS_PX);
#endif
        float span = max(radiusPx - AO_MIN_STEP_PX, 0.0);
#if AO_METHOD == 1
        float shift = (AO_HALF_PI - gamma) / AO_PI;
        uint mask = 0u;
#if AO_UNION_EXACT
        float starts[2 * AO_STEPS];
        float ends[2 * AO_STEPS];
        for (int i = 0; i < 2 * AO_STEPS; i++) { starts[i] = 0.0; ends[i] = 0.0; }
#endif
#else
        float horizon[2];
        horizon[0] = AO_HALF_PI + gamma;  // side +1 (methods/gtao.py ExactGTAOAccumulator.begin_slice)
        horizon[1] = AO_HALF_PI - gamma;  // side -1
#endif
        for (int sideIndex = 0; sideIndex < 2; sideIndex++) {
            float side = sideIndex == 0 ? 1.0 : -1.0;
            float xi = noiseStep;
#if AO_STAGGER
            // walk/patterns.py staggered_offset: each half-slice's steps shifted by 1 / (2 slices) of a step
            xi = frac(xi + (float(s) + 0.5 * float(sideIndex)) / float(AO_SLICES));
#endif
            for (int j = 0; j < AO_STEPS; j++) {
                // SlicePattern.step_offsets
                float fraction = (float(j) + xi) / float(AO_STEPS);
#if AO_STEP_POWER_ONE == 0
                fraction = pow(fraction, AO_STEP_POWER);
#endif
                float2 offset = (AO_MIN_STEP_PX + span * fraction) * (dir * side);
                AOSample f = aoFetch(u + offset.x, v + offset.y, px, py, intr);
                float3 delta = f.position - P;
                if (!(f.valid && dot(delta, delta) > AO_MIN_OFFSET * AO_MIN_OFFSET * d * d)) continue;  // (Sample.valid)
                float av = dot(delta, V);
                float at = side * dot(delta, T);
#if AO_METHOD == 1
                // the thickness model at the sample (thickness.py)
#if AO_THICKNESS_MODEL == 0
                float t = AO_THICKNESS;
#elif AO_THICKNESS_MODEL == 1
                float t = AO_THICKNESS + AO_THICKNESS_SLOPE * (-f.position.z);
#else
                float t = AO_THICKNESS_SCALE * f.layer + AO_THICKNESS;
#endif
#ifdef AO_THICKNESS_GROWTH
                t = t * (1.0 + AO_THICKNESS_GROWTH * length(delta));
#endif
                // intervals.py back_point
#if AO_THICKNESS_DEPTH
                float k = t / (-f.position.z);
                float bv = av + k * (av - length(P));
                float bt = at * (1.0 + k);
#else
                float bv = av - t;
                float bt = at;
#endif
                float fv2 = av;
                float ft2 = at;
#if AO_CLIP_TO_RADIUS
                // intervals.py clip_to_sphere
                float ev = bv - fv2;
                float et = bt - ft2;
                float qa = ev * ev + et * et;
                float qb = fv2 * ev + ft2 * et;
                float qc = fv2 * fv2 + ft2 * ft2 - AO_RADIUS * AO_RADIUS;
                float disc = qb * qb - qa * qc;
                bool degenerate = qa <= 1e-30 * max(fv2 * fv2 + ft2 * ft2, 1e-30);
                bool hit = disc > 0.0 && !degenerate;
                float root = sqrt(hit ? disc : 1.0);
                float safeA = hit ? qa : 1.0;
                float w0 = hit ? clamp((-qb - root) / safeA, 0.0, 1.0) : 0.0;
                float w1 = hit ? clamp((-qb + root) / safeA, 0.0, 1.0) : 1.0;
                bool inSphere = degenerate ? qc <= 0.0 : (hit && w1 > w0);
                if (!inSphere) continue;
                fv2 = av + w0 * ev;
                ft2 = at + w0 * et;
                bv = av + w1 * ev;
                bt = at + w1 * et;
#endif
                // methods/bitmask.py _unit_positions and _between
                float xf = clamp(shift + atan2(ft2, fv2) * (side / AO_PI), 0.0, 1.0);
                float xb = clamp(shift + atan2(bt, bv) * (side / AO_PI), 0.0, 1.0);
                float lo = side > 0.0 ? xf : xb;
                float hi = side > 0.0 ? xb : xf;
                float start = lo * 32.0;
                float width = (hi - lo) * 32.0 - AO_SECTOR_EPSILON;
#if AO_UNION_EXACT
                if (width > 0.0) {
                    starts[sideIndex * AO_STEPS + j] = clamp(start, 0.0, 32.0);
                    ends[sideIndex * AO_STEPS + j] = clamp(start + width, 0.0, 32.0);
                }
#else
                mask = mask | aoSectorBits(start, width);
#endif
#else
                // methods/gtao.py ExactGTAOAccumulator.step
                float bound = AO_HALF_PI + side * gamma;
                float theta = clamp(atan2(at, av), 0.0, AO_PI);
                float dist = length(delta);
#if AO_FALLOFF_ON
                float w = clamp((AO_RADIUS - dist) / max(AO_FALLOFF_RANGE * AO_RADIUS, 1e-12), 0.0, 1.0);
#else
                float w = dist < AO_RADIUS ? 1.0 : 0.0;
#endif
                horizon[sideIndex] = min(horizon[sideIndex], bound + w * (theta - bound));
#endif
            }
        }
#if AO_METHOD == 1
#if AO_UNION_EXACT
        // intervals.py union_measure: sorted by start, each interval adds the part not yet covered
        for (int a = 1; a < 2 * AO_STEPS; a++) {
            for (int b = a; b > 0; b--) {
                if (starts[b] < starts[b - 1]) {
                    float ts = starts[b]; starts[b] = starts[b - 1]; starts[b - 1] = ts;
                    float te = ends[b]; ends[b] = ends[b - 1]; ends[b - 1] = te;
                }
            }
        }
        float reach = 0.0;
        float covered = 0.0;
        for (int i = 0; i < 2 * AO_STEPS; i++) {
            float a0 = max(starts[i], reach);
            float b0 = max(ends[i], reach);
#if AO_WEIGHTING_COSINE
            covered += aoCosineMeasure(b0, gamma, len) - aoCosineMeasure(a0, gamma, len);
#else
            covered += b0 - a0;
#endif
            reach = max(reach, ends[i]);
        }
#if AO_WEIGHTING_COSINE
        float total = aoCosineMeasure(32.0, gamma, len);
        sumVis += total - covered;
        sumDen += total;
#else
        sumVis += 1.0 - covered / 32.0;
#endif
#else
#if AO_WEIGHTING_COSINE
        // methods/bitmask_common.py cosine_sector_weights
        float edge = aoArcMeasure(gamma - AO_HALF_PI, gamma);
        for (int k = 0; k < 32; k++) {
            float next = aoArcMeasure(gamma - AO_HALF_PI + AO_PI * float(k + 1) / 32.0, gamma);
            float weight = max(next - edge, 0.0) * len;
            edge = next;
            sumDen += weight;
            if (((mask >> uint(k)) & 1u) == 0u) sumVis += weight;
        }
#else
        sumVis += float(32 - aoPopcount(mask)) / 32.0;
#endif
#endif
#else
        // methods/gtao.py GTAOAccumulator.end_slice (ops.py arc_integral)
        float h1 = max(-horizon[1], gamma - AO_HALF_PI);
        float h2 = min(horizon[0], gamma + AO_HALF_PI);
        float cn = cos(gamma);
        float sn = sin(gamma);
        float lo1 = gamma - AO_HALF_PI;
        float hi1 = gamma + AO_HALF_PI;
        sumVis += len * 0.25 * ((-cos(2.0 * h1 - gamma) + cn + 2.0 * h1 * sn) + (-cos(2.0 * h2 - gamma) + cn + 2.0 * h2 * sn));
        sumDen += len * 0.25 * ((-cos(2.0 * lo1 - gamma) + cn + 2.0 * lo1 * sn) + (-cos(2.0 * hi1 - gamma) + cn + 2.0 * hi1 * sn));
#endif
    }
    // finish
#if AO_METHOD == 1
#if AO_WEIGHTING_COSINE
    return sumVis / max(sumDen, 1e-30);
#else
    return sumVis / float(AO_SLICES);
#endif
#else
#if AO_NORMALIZE == 0
    float vis = sumVis / max(sumDen, 1e-12);
#elif AO_NORMALIZE == 1
    float vis = sumVis / float(AO_SLICES);
#else
    float vis = sumVis / float(AO_SLICES) * (2.0 / AO_PI);
#endif
    vis = clamp(vis, 0.0, 1.0);
#if AO_FINAL_POWER_ONE == 0
    vis = pow(clamp(vis, 1e-12, 1.0), AO_FINAL_POWER);
#endif
#if AO_MULTIBOUNCE
    // methods/gtao.py multibounce
    float mbA = 2.0404 * AO_ALBEDO - 0.3324;
    float mbB = -4.7951 * AO_ALBEDO + 0.6417;
    float mbC = 2.7552 * AO_ALBEDO + 0.6903;
    vis = max(vis, ((vis * mbA + mbB) * vis + mbC) * vis);
#endif
    return clamp(vis, 0.0, 1.0);
#endif
}
"""
