// MKL's vector math, which torch's unary functions (cos, sin, acos, asin, sqrt) call on a build with MKL
// (the functions live inside libtorch_cpu): kernels that must match torch bit for bit call them too. Built
// with -DTORCH_AO_MKL_VML where torch.backends.mkl.is_available() (torch_ao/kernels/build.py).
#pragma once

#ifdef TORCH_AO_MKL_VML
extern "C" void vmsCos(int n, const float* a, float* r, long long mode);
extern "C" void vmsSin(int n, const float* a, float* r, long long mode);
extern "C" void vmsAcos(int n, const float* a, float* r, long long mode);
extern "C" void vmsAsin(int n, const float* a, float* r, long long mode);
extern "C" void vmsSqrt(int n, const float* a, float* r, long long mode);
extern "C" int MKL_Set_Num_Threads_Local(int n);
constexpr long long kVmlMode = 0x2 | 0x140000 | 0x100;  // VML_HA | VML_FTZDAZ_OFF | VML_ERRMODE_IGNORE, as ATen
#endif
