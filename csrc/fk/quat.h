// The quaternion math of the FK kernels (w, x, y, z), one definition for the CPU (cpu.cpp) and the CUDA (cuda.cu)
// kernels: host functions in C++ (the CPU build, the CUDA emulator's host build), host and device under nvcc.
#pragma once

#if defined(__CUDACC__)
#define MODI_FK_QUAT __host__ __device__ __forceinline__
#else
#define MODI_FK_QUAT inline
#endif

namespace modi_ext {
namespace fk {

// out = a (x) b (Hamilton product).
template <typename T>
MODI_FK_QUAT void qmul(const T* a, const T* b, T* out) {
  const T aw = a[0], ax = a[1], ay = a[2], az = a[3];
  const T bw = b[0], bx = b[1], by = b[2], bz = b[3];
  out[0] = aw * bw - ax * bx - ay * by - az * bz;
  out[1] = aw * bx + ax * bw + ay * bz - az * by;
  out[2] = aw * by - ax * bz + ay * bw + az * bx;
  out[3] = aw * bz + ax * by - ay * bx + az * bw;
}

// out = v + 2w (u x v) + 2 u x (u x v); passing -u applies the transpose of that linear map.
template <typename T>
MODI_FK_QUAT void qrot(T w, T ux, T uy, T uz, const T* v, T* out) {
  const T tx = T(2) * (uy * v[2] - uz * v[1]);
  const T ty = T(2) * (uz * v[0] - ux * v[2]);
  const T tz = T(2) * (ux * v[1] - uy * v[0]);
  out[0] = v[0] + w * tx + (uy * tz - uz * ty);
  out[1] = v[1] + w * ty + (uz * tx - ux * tz);
  out[2] = v[2] + w * tz + (ux * ty - uy * tx);
}

// The backward of P[j] = P[p] + A(Q[p], o), A = o + 2w (u x o) + 2u (u.o) - 2o (u.u), Q[p] = (w, u), towards the
// parent's rotation: given g = dL/dP[j], out = (dL/dw, dL/du) with
//   dL/dw = 2 g.(u x o),   dL/du = 2w (o x g) + 2 (u.o) g + 2 (g.u) o - 4 (g.o) u.
// (dL/do = A((w, -u), g): qrot with -u.)
template <typename T>
MODI_FK_QUAT void position_grad(T w, T ux, T uy, T uz, const T* o, T gx, T gy, T gz, T* out) {
  const T uxo_x = uy * o[2] - uz * o[1], uxo_y = uz * o[0] - ux * o[2], uxo_z = ux * o[1] - uy * o[0];
  const T oxg_x = o[1] * gz - o[2] * gy, oxg_y = o[2] * gx - o[0] * gz, oxg_z = o[0] * gy - o[1] * gx;
  const T u_o = ux * o[0] + uy * o[1] + uz * o[2];
  const T g_u = gx * ux + gy * uy + gz * uz;
  const T g_o = gx * o[0] + gy * o[1] + gz * o[2];
  out[0] = T(2) * (gx * uxo_x + gy * uxo_y + gz * uxo_z);
  out[1] = T(2) * (w * oxg_x + u_o * gx + g_u * o[0]) - T(4) * g_o * ux;
  out[2] = T(2) * (w * oxg_y + u_o * gy + g_u * o[1]) - T(4) * g_o * uy;
  out[3] = T(2) * (w * oxg_z + u_o * gz + g_u * o[2]) - T(4) * g_o * uz;
}

}  // namespace fk
}  // namespace modi_ext
