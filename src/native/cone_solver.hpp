// The time-stepper's cone solver, rendered for the native kernel: integrators/cone_solver.py is the specification.
//
// Newton's method on the natural map of Coulomb's law (De Saxcé's correction on each cone), with a backtracking line
// search, and nonsmooth Gauss–Seidel as the fallback. Every operation is the Python module's, in its order: sums
// start at +0.0 and add their products in index order, elementwise expressions are written as numpy evaluates
// them, so both kernels compute the same impulses bit for bit. Dense and small (tens of rows): plain loops, no
// allocation once the workspace has grown to the largest problem.
#pragma once

#include <algorithm>
#include <cmath>
#include <cstring>
#include <vector>

#include <Eigen/Core>

namespace multibody_sim
{
  namespace cone
  {
    enum BlockKind : int
    {
      CONE = 0,      // 3 rows: t1, t2, n; ‖λ_t‖ ≤ μ λ_n
      HALFLINE = 1,  // 1 row: λ ≥ 0
      INTERVAL = 2,  // 1 row: |λ| ≤ bound
    };

    // cone_solver.py's constants (the ContactScene's data carries them from Python)
    struct Settings
    {
      double tolerance = 0.0, fallback_tolerance = 0.0, regularization = 0.0, damping = 0.0, armijo = 0.0;
      double shortest_step = 0.0, proximal = 0.0, relaxation = 0.0, rho_power = 0.0, rho_step = 0.0;
      double rho_balance = 0.0, rho_min = 0.0, rho_max = 0.0;
      int newton_iterations = 0, fallback_rounds = 0, local_iterations = 0;
    };

    struct Block
    {
      int kind = CONE, start = 0;
      double param = 0.0;  // μ, or the interval's bound
    };

    using Matrix = Eigen::Matrix<double, Eigen::Dynamic, Eigen::Dynamic, Eigen::RowMajor>;
    using Vector = Eigen::VectorXd;

    struct Solution
    {
      bool converged = false, fallback = false;
      int iterations = 0;
      double residual = 0.0;
    };

    // cone_solver.project_cones for one cone, in place
    inline void project_cone(double & t1, double & t2, double & n, double mu)
    {
      const double tn = std::sqrt(t1 * t1 + t2 * t2);
      if (tn <= mu * n)
        return;
      if (mu * tn <= -n)
      {
        t1 = t2 = n = 0.0;
        return;
      }
      const double a = (mu * tn + n) / (mu * mu + 1.0);
      const double scale = mu * a / tn;
      t1 = scale * t1;
      t2 = scale * t2;
      n = a;
    }

    // Gaussian elimination with partial pivoting (the first largest pivot) of the p x p row-major A (row stride
    // `stride`) and b, in place: cone_solver.lu_solve's, each element's operations in its order. Built for AVX2 too
    // where the machine has it (the same IEEE products and differences, four at a time: the same bits).
    __attribute__((target_clones("avx2", "default"))) static void eliminate(double * A, double * b, int p, int stride)
    {
      for (int j = 0; j < p; ++j)
      {
        int k = j;
        double top = std::abs(A[j * stride + j]);
        for (int i = j + 1; i < p; ++i)  // np.argmax: the first of the largest
          if (std::abs(A[i * stride + j]) > top)
          {
            top = std::abs(A[i * stride + j]);
            k = i;
          }
        if (k != j)
        {
          std::swap_ranges(A + j * stride, A + j * stride + p, A + k * stride);
          std::swap(b[j], b[k]);
        }
        const double * pivot = A + j * stride;
        for (int i = j + 1; i < p; ++i)
        {
          double * row = A + i * stride;
          const double f = row[j] / pivot[j];
          for (int c = j + 1; c < p; ++c)
            row[c] -= f * pivot[c];
          b[i] -= f * b[j];
        }
      }
    }

    class Solver
    {
    public:
      // ---- cone_solver.project / de_saxce / block_scales / residual ---------------------------------------------
      static void project(const std::vector<Block> & blocks, Vector & x)
      {
        for (const Block & b : blocks)
        {
          const int s = b.start;
          if (b.kind == CONE)
            project_cone(x[s], x[s + 1], x[s + 2], b.param);
          else if (b.kind == HALFLINE)
            x[s] = x[s] > 0.0 ? x[s] : 0.0;
          else
            x[s] = x[s] > b.param ? b.param : (x[s] < -b.param ? -b.param : x[s]);
        }
      }

      // u + Φ(u) into t (u + 0.0 on the rows without a correction, as numpy adds its zeros)
      static void add_de_saxce(const std::vector<Block> & blocks, const Vector & u, Vector & t)
      {
        const int m = static_cast<int>(u.size());
        t.resize(m);
        for (int i = 0; i < m; ++i)
          t[i] = u[i] + 0.0;
        for (const Block & b : blocks)
          if (b.kind == CONE)
          {
            const int s = b.start;
            t[s + 2] = u[s + 2] + b.param * std::sqrt(u[s] * u[s] + u[s + 1] * u[s + 1]);
          }
      }

      static void block_scales(const std::vector<Block> & blocks, const Matrix & G, Vector & scales)
      {
        const int m = static_cast<int>(G.rows());
        scales.resize(m);
        for (int i = 0; i < m; ++i)
          scales[i] = G(i, i);
        for (const Block & b : blocks)
          if (b.kind == CONE)
          {
            const int s = b.start;
            const double mean = ((scales[s] + scales[s + 1]) + scales[s + 2]) / 3.0;
            scales[s] = scales[s + 1] = scales[s + 2] = mean;
          }
      }

      // matvec(A, x) + b into out (each row's products summed in column order from +0.0; four rows at a time, each
      // its own sum, so that the additions of different rows overlap)
      static void affine(const Matrix & A, const Vector & x, const Vector & b, Vector & out)
      {
        const int m = static_cast<int>(A.rows()), n = static_cast<int>(A.cols());
        const double * xs = x.data();
        int i = 0;
        for (; i + 4 <= m; i += 4)
        {
          const double *r0 = A.row(i).data(), *r1 = r0 + n, *r2 = r1 + n, *r3 = r2 + n;
          double s0 = 0.0, s1 = 0.0, s2 = 0.0, s3 = 0.0;
          for (int j = 0; j < n; ++j)
          {
            const double xj = xs[j];
            s0 += r0[j] * xj;
            s1 += r1[j] * xj;
            s2 += r2[j] * xj;
            s3 += r3[j] * xj;
          }
          out[i] = s0 + b[i];
          out[i + 1] = s1 + b[i + 1];
          out[i + 2] = s2 + b[i + 2];
          out[i + 3] = s3 + b[i + 3];
        }
        for (; i < m; ++i)
        {
          const double * row = A.row(i).data();
          double s = 0.0;
          for (int j = 0; j < n; ++j)
            s += row[j] * xs[j];
          out[i] = s + b[i];
        }
      }

      // affine(G, x, g) into out, the latest result reused when G and g are the same arrays of the same solve and
      // x has the same bits (the solve's candidates repeat the natural map's x: its projection leaves an iterate
      // inside K as it is). forget() ends a problem's reuse (solve(), and each block a sweep solves).
      void affine_of(const Matrix & G, const Vector & x, const Vector & g, Vector & out)
      {
        const int m = static_cast<int>(x.size());
        if (memo_valid_ && memo_G_ == G.data() && memo_g_ == g.data() && memo_x_.size() == m
            && std::equal(x.data(), x.data() + m, memo_x_.data(),
                          [](double a, double b) { return std::memcmp(&a, &b, sizeof(double)) == 0; }))
        {
          out = memo_u_;
          return;
        }
        affine(G, x, g, out);
        memo_valid_ = true;
        memo_G_ = G.data();
        memo_g_ = g.data();
        memo_x_ = x;
        memo_u_ = out;
      }

      void forget() { memo_valid_ = false; }

      double residual(const std::vector<Block> & blocks, const Vector & lam, const Vector & u, const Vector & scales)
      {
        const int m = static_cast<int>(lam.size());
        if (!m)
          return 0.0;
        add_de_saxce(blocks, u, t_);
        diff_.resize(m);
        for (int i = 0; i < m; ++i)
          diff_[i] = lam[i] - t_[i] / scales[i];
        project(blocks, diff_);
        for (int i = 0; i < m; ++i)
          diff_[i] = lam[i] - diff_[i];
        // np.max over the cones, then over the single rows (max(worst, that))
        double cones = 0.0, singles = 0.0;
        bool any_cone = false, any_single = false;
        for (const Block & b : blocks)
        {
          const int s = b.start;
          if (b.kind == CONE)
          {
            const double d0 = diff_[s], d1 = diff_[s + 1], d2 = diff_[s + 2];
            const double x = scales[s] * std::sqrt((d0 * d0 + d1 * d1) + d2 * d2);
            cones = !any_cone ? x : (x > cones || std::isnan(x) ? x : cones);
            any_cone = true;
          }
        }
        // the single rows in numpy's order: half-lines first, then intervals
        for (int pass = HALFLINE; pass <= INTERVAL; ++pass)
          for (const Block & b : blocks)
            if (b.kind == pass)
            {
              const double x = scales[b.start] * std::abs(diff_[b.start]);
              singles = !any_single ? x : (x > singles || std::isnan(x) ? x : singles);
              any_single = true;
            }
        double worst = any_cone ? cones : 0.0;
        if (any_single)
          worst = singles > worst ? singles : worst;  // Python's max(worst, singles)
        return worst;
      }

      // ---- cone_solver.lu_solve: A is overwritten ----------------------------------------------------------------
      void lu_solve(Matrix & A, Vector & b, Vector & x)
      {
        const int p = static_cast<int>(b.size());
        eliminate(A.data(), b.data(), p, static_cast<int>(A.outerStride()));
        x.resize(p);
        for (int i = p - 1; i >= 0; --i)
        {
          double s = 0.0;
          for (int c = i + 1; c < p; ++c)
            s += A(i, c) * x[c];
          x[i] = (b[i] - s) / A(i, i);
        }
      }

      // ---- cone_solver.cholesky / cholesky_solve ----------------------------------------------------------------
      static void cholesky(const Matrix & A, Matrix & L)
      {
        const int m = static_cast<int>(A.rows());
        L.setZero(m, m);
        for (int j = 0; j < m; ++j)
        {
          double s = 0.0;
          for (int k = 0; k < j; ++k)
            s += L(j, k) * L(j, k);
          L(j, j) = std::sqrt(A(j, j) - s);
          for (int i = j + 1; i < m; ++i)
          {
            double t = 0.0;
            for (int k = 0; k < j; ++k)
              t += L(i, k) * L(j, k);
            L(i, j) = (A(i, j) - t) / L(j, j);
          }
        }
      }

      static void cholesky_solve(const Matrix & L, const Vector & b, Vector & y, Vector & x)
      {
        const int m = static_cast<int>(b.size());
        y.resize(m);
        x.resize(m);
        for (int i = 0; i < m; ++i)
        {
          double s = 0.0;
          for (int k = 0; k < i; ++k)
            s += L(i, k) * y[k];
          y[i] = (b[i] - s) / L(i, i);
        }
        for (int i = m - 1; i >= 0; --i)
        {
          double s = 0.0;
          for (int k = i + 1; k < m; ++k)
            s += L(k, i) * x[k];
          x[i] = (y[i] - s) / L(i, i);
        }
      }

      // ---- Newton on the natural map -----------------------------------------------------------------------------
      // (F, u, y) of λ
      void natural_map(
        const Matrix & G, const Vector & g, const std::vector<Block> & blocks, const Vector & scales,
        const Vector & lam, Vector & F, Vector & u, Vector & y)
      {
        const int m = static_cast<int>(g.size());
        u.resize(m);
        y.resize(m);
        F.resize(m);
        affine_of(G, lam, g, u);
        add_de_saxce(blocks, u, t_);
        for (int i = 0; i < m; ++i)
          y[i] = lam[i] - t_[i] / scales[i];
        F = y;
        project(blocks, F);
        for (int i = 0; i < m; ++i)
          F[i] = lam[i] - F[i];
      }

      static void cone_jacobian(double t1, double t2, double n, double mu, double (&out)[3][3])
      {
        const double tn = std::sqrt(t1 * t1 + t2 * t2);
        for (auto & row : out)
          for (double & x : row)
            x = 0.0;
        if (tn <= mu * n)
        {
          out[0][0] = out[1][1] = out[2][2] = 1.0;
          return;
        }
        if (mu * tn <= -n)
          return;
        const double c = mu * mu + 1.0;
        const double a = (mu * tn + n) / c;
        const double h[2] = {t1 / tn, t2 / tn};
        const double k = mu * a / tn;
        const double m2 = mu * mu;
        for (int i = 0; i < 2; ++i)
        {
          for (int j = 0; j < 2; ++j)
          {
            const double hh = h[i] * h[j];
            out[i][j] = (m2 * hh) / c + k * ((i == j ? 1.0 : 0.0) - hh);
          }
          out[i][2] = mu * h[i] / c;
          out[2][i] = mu * h[i] / c;
        }
        out[2][2] = 1.0 / c;
      }

      // cone_solver.newton_matrix into H_
      void newton_matrix(
        const Matrix & G, const std::vector<Block> & blocks, const Vector & scales, const Vector & u,
        const Vector & y, double damping)
      {
        const int m = static_cast<int>(u.size());
        A_ = G;
        for (const Block & b : blocks)
          if (b.kind == CONE)
          {
            const int t1 = b.start, t2 = b.start + 1, n = b.start + 2;
            const double s1 = u[t1], s2 = u[t2];
            const double slip = std::sqrt(s1 * s1 + s2 * s2);
            if (slip > 0.0)
            {
              const double c1 = b.param * s1 / slip, c2 = b.param * s2 / slip;
              for (int c = 0; c < m; ++c)
                A_(n, c) = G(n, c) + (c1 * G(t1, c) + c2 * G(t2, c));
            }
          }
        B_.resize(m, m);
        for (int r = 0; r < m; ++r)
          for (int c = 0; c < m; ++c)
            B_(r, c) = (r == c ? 1.0 : 0.0) - A_(r, c) / scales[r];
        H_.resize(m, m);  // C, then I - C
        regularized_.assign(static_cast<size_t>(m), false);
        for (const Block & b : blocks)
        {
          const int s = b.start;
          if (b.kind == CONE)
          {
            double P[3][3];
            cone_jacobian(y[s], y[s + 1], y[s + 2], b.param, P);
            for (int i = 0; i < 3; ++i)
              for (int c = 0; c < m; ++c)
                H_(s + i, c) = (P[i][0] * B_(s, c) + P[i][1] * B_(s + 1, c)) + P[i][2] * B_(s + 2, c);
            const bool on = P[2][2] != 0.0;
            regularized_[static_cast<size_t>(s)] = regularized_[static_cast<size_t>(s + 1)] =
              regularized_[static_cast<size_t>(s + 2)] = on;
          }
          else
          {
            const bool on = b.kind == HALFLINE ? y[s] > 0.0 : (-b.param < y[s] && y[s] < b.param);
            regularized_[static_cast<size_t>(s)] = on;
            const double p = on ? 1.0 : 0.0;
            for (int c = 0; c < m; ++c)
              H_(s, c) = p * B_(s, c);
          }
        }
        for (int r = 0; r < m; ++r)
          for (int c = 0; c < m; ++c)
            H_(r, c) = (r == c ? 1.0 : 0.0) - H_(r, c);
        for (int r = 0; r < m; ++r)
          if (regularized_[static_cast<size_t>(r)])
            H_(r, r) += damping;
      }

      static double dot(const Vector & a, const Vector & b)  // zsum(a * b)
      {
        double s = 0.0;
        for (int i = 0; i < a.size(); ++i)
          s += a[i] * b[i];
        return s;
      }

      // (λ projected onto K, its residual) into candidate / return value
      double candidate(
        const Matrix & G, const Vector & g, const std::vector<Block> & blocks, const Vector & scales,
        const Vector & lam, Vector & out)
      {
        out = lam;
        project(blocks, out);
        uc_.resize(g.size());
        affine_of(G, out, g, uc_);
        return residual(blocks, out, uc_, scales);
      }

      // cone_solver.newton: best into `best`, its residual returned, iterations into `taken`
      double newton(
        const Matrix & G, const Vector & g, const std::vector<Block> & blocks, const Vector & scales,
        const Vector & start, double tolerance, int iterations, Vector & best, int & taken)
      {
        Work & w = work_[depth_++];
        lam_guard guard{depth_};
        w.lam = start;
        natural_map(G, g, blocks, scales, w.lam, w.F, w.u, w.y);
        double best_r = candidate(G, g, blocks, scales, w.lam, best);
        double damping = settings.regularization;
        taken = 0;
        const int m = static_cast<int>(g.size());
        while (best_r > tolerance && taken < iterations)
        {
          newton_matrix(G, blocks, scales, w.u, w.y, damping);
          w.rhs.resize(m);
          for (int i = 0; i < m; ++i)
            w.rhs[i] = -w.F[i];
          lu_solve(H_, w.rhs, w.d);
          taken += 1;
          const double f0 = dot(w.F, w.F);
          double step = 1.0;
          w.trial.resize(m);
          while (true)
          {
            for (int i = 0; i < m; ++i)
              w.trial[i] = w.lam[i] + step * w.d[i];
            natural_map(G, g, blocks, scales, w.trial, w.Ft, w.ut, w.yt);
            if (dot(w.Ft, w.Ft) <= (1.0 - settings.armijo * step) * f0 || step < settings.shortest_step)
              break;
            step = 0.5 * step;
          }
          if (step < 1.0 && damping < settings.damping)  // shortened: damp, and try again from λ
          {
            damping = settings.damping;
            continue;
          }
          if (step < settings.shortest_step)
            break;
          if (step == 1.0)
            damping = settings.regularization;
          std::swap(w.lam, w.trial);
          std::swap(w.F, w.Ft);
          std::swap(w.u, w.ut);
          std::swap(w.y, w.yt);
          const double r = candidate(G, g, blocks, scales, w.lam, w.cand);
          if (r < best_r)
          {
            best = w.cand;
            best_r = r;
          }
        }
        return best_r;
      }

      // ---- cone_solver.Sweeps.step: one sweep, in place on lam ---------------------------------------------------
      void sweep(
        const Matrix & G, const Vector & g, const std::vector<Block> & blocks, const Vector & scales, Vector & lam,
        double tolerance)
      {
        const int m = static_cast<int>(g.size());
        for (const Block & b : blocks)
        {
          const int s = b.start, size = b.kind == CONE ? 3 : 1;
          q_.resize(size);
          for (int i = 0; i < size; ++i)  // the other blocks' impulses applied (this block's columns skipped)
          {
            double sum = 0.0;
            for (int c = 0; c < m; ++c)
              if (c < s || c >= s + size)
                sum += G(s + i, c) * lam[c];
            q_[i] = sum + g[s + i];
          }
          if (b.kind == CONE)
          {
            local_G_ = G.block(s, s, 3, 3);
            local_scales_ = scales.segment(s, 3);
            local_start_ = lam.segment(s, 3);
            local_blocks_.assign(1, Block{CONE, 0, b.param});
            forget();  // local_G_ and q_ hold this block's problem now
            int taken = 0;
            newton(local_G_, q_, local_blocks_, local_scales_, local_start_, tolerance, settings.local_iterations,
                   local_best_, taken);
            lam.segment(s, 3) = local_best_;
          }
          else
          {
            const double x = -q_[0] / G(s, s);
            if (b.kind == HALFLINE)
              lam[s] = x > 0.0 ? x : 0.0;
            else
              lam[s] = x > b.param ? b.param : (x < -b.param ? -b.param : x);
          }
        }
      }

      // ---- cone_solver.Admm -------------------------------------------------------------------------------------
      void admm_start(const Matrix & G, const Vector & g, const std::vector<Block> & blocks, const Vector & lam)
      {
        const int m = static_cast<int>(g.size());
        double largest = 0.0;
        for (int i = 0; i < m; ++i)  // Gershgorin's bound: np.max(zsum(|G|, axis=1))
        {
          double s = 0.0;
          for (int j = 0; j < m; ++j)
            s += std::abs(G(i, j));
          largest = i == 0 ? s : (s > largest || std::isnan(s) ? s : largest);
        }
        mu_ = settings.proximal * largest;
        const double cond = largest / mu_;
        double rho = std::sqrt(largest * mu_) * std::pow(cond, settings.rho_power);
        rho = settings.rho_min > rho ? settings.rho_min : rho;  // min(max(rho, RHO_MIN), RHO_MAX)
        rho_ = settings.rho_max < rho ? settings.rho_max : rho;
        factor_ = std::pow(cond, settings.rho_step);
        ax_ = lam;
        ay_ = lam;
        project(blocks, ay_);
        az_.resize(m);
        affine(G, ay_, g, az_);
        add_de_saxce(blocks, az_, t_);
        az_ = t_;
        admm_factor(G);
      }

      void admm_factor(const Matrix & G)
      {
        const int m = static_cast<int>(G.rows());
        const double c = mu_ + settings.relaxation * rho_;
        A_.resize(m, m);
        for (int i = 0; i < m; ++i)
          for (int j = 0; j < m; ++j)
            A_(i, j) = G(i, j) + (i == j ? c * 1.0 : c * 0.0);
        cholesky(A_, chol_);
      }

      // one iteration: the projected iterate into ay_
      void admm_step(const Matrix & G, const Vector & g, const std::vector<Block> & blocks)
      {
        const int m = static_cast<int>(g.size());
        const double tr = settings.relaxation * rho_;
        ax_prev_ = ax_;
        az_prev_ = az_;
        for (int i = 0; i < m; ++i)
          ay_[i] = ax_prev_[i] - az_prev_[i] / tr;
        project(blocks, ay_);
        // rhs = -((((g + Φ(z_prev)) - tr y) - mu x_prev) - z_prev)
        phi_.setZero(m);
        for (const Block & b : blocks)
          if (b.kind == CONE)
          {
            const int s = b.start;
            phi_[s + 2] = b.param * std::sqrt(az_prev_[s] * az_prev_[s] + az_prev_[s + 1] * az_prev_[s + 1]);
          }
        arhs_.resize(m);
        for (int i = 0; i < m; ++i)
          arhs_[i] = -((((g[i] + phi_[i]) - tr * ay_[i]) - mu_ * ax_prev_[i]) - az_prev_[i]);
        cholesky_solve(chol_, arhs_, ty_, ax_);
        double primal = 0.0, dx = 0.0;
        for (int i = 0; i < m; ++i)
        {
          az_[i] = az_prev_[i] - tr * (ax_[i] - ay_[i]);
          const double p = std::abs(ax_[i] - ay_[i]), d = std::abs(ax_[i] - ax_prev_[i]);
          primal = i == 0 ? p : (p > primal || std::isnan(p) ? p : primal);
          dx = i == 0 ? d : (d > dx || std::isnan(d) ? d : dx);
        }
        const double dual = (tr > mu_ ? tr : mu_) * dx;  // max(mu, tr) * max|x - x_prev|
        double rho = rho_;
        if (primal > settings.rho_balance * dual)
          rho = rho * factor_;
        else if (dual > settings.rho_balance * primal)
          rho = rho / factor_;
        rho = settings.rho_min > rho ? settings.rho_min : rho;
        rho = settings.rho_max < rho ? settings.rho_max : rho;
        if (rho != rho_)
        {
          rho_ = rho;
          admm_factor(G);
        }
      }

      // ---- cone_solver.solve: the impulses into lam --------------------------------------------------------------
      Solution solve(
        const Matrix & G, const Vector & g, const std::vector<Block> & blocks, const Vector & guess, double scale,
        int max_iterations, bool pgs, Vector & lam)
      {
        Solution out;
        forget();
        const double tolerance = settings.tolerance * scale;
        block_scales(blocks, G, scales_);
        double r = candidate(G, g, blocks, scales_, guess, lam);
        int taken = 0;
        if (r <= tolerance)
        {
          out.converged = true;
          out.residual = r;
          return out;
        }
        if (!pgs)
        {
          first_ = lam;
          r = newton(G, g, blocks, scales_, first_, tolerance, std::min(settings.newton_iterations, max_iterations),
                     lam, taken);
          if (r <= tolerance)
          {
            out.converged = true;
            out.iterations = taken;
            out.residual = r;
            return out;
          }
        }
        best_ = lam;
        double best_r = r;
        if (pgs)
          sweep_lam_ = lam;
        else
          admm_start(G, g, blocks, lam);
        int rounds = 0, next_newton = settings.fallback_rounds;
        while (taken < max_iterations)
        {
          if (pgs)
          {
            sweep(G, g, blocks, scales_, sweep_lam_, tolerance);
            iterate_ = sweep_lam_;
          }
          else
          {
            admm_step(G, g, blocks);
            iterate_ = ay_;
          }
          rounds += 1;
          taken += 1;
          r = candidate(G, g, blocks, scales_, iterate_, cand_);
          if (r < best_r)
          {
            best_ = cand_;
            best_r = r;
          }
          if (r <= tolerance)
            break;
          if (rounds == next_newton && taken < max_iterations)
          {
            next_newton *= 4;
            int n = 0;
            r = newton(G, g, blocks, scales_, iterate_, tolerance,
                       std::min(settings.newton_iterations, max_iterations - taken), found_, n);
            taken += n;
            if (r < best_r)
            {
              best_ = found_;
              best_r = r;
            }
            if (r <= tolerance)
              break;
          }
        }
        lam = best_;
        out.converged = best_r <= settings.fallback_tolerance * scale;
        out.fallback = true;
        out.iterations = taken;
        out.residual = best_r;
        return out;
      }

      Settings settings;

    private:
      struct Work  // one Newton's vectors (the sweep's local Newton runs inside the fallback, one level down)
      {
        Vector lam, F, u, y, Ft, ut, yt, trial, d, rhs, cand;
      };
      struct lam_guard
      {
        int & depth;
        ~lam_guard() { --depth; }
      };
      Work work_[2];
      int depth_ = 0;
      Matrix A_, B_, H_, local_G_, chol_;
      bool memo_valid_ = false;  // affine_of's latest (G, g, x) -> u
      const double *memo_G_ = nullptr, *memo_g_ = nullptr;
      Vector memo_x_, memo_u_;
      double mu_ = 0.0, rho_ = 0.0, factor_ = 0.0;
      Vector ax_, ay_, az_, ax_prev_, az_prev_, phi_, arhs_, ty_, sweep_lam_, iterate_;
      std::vector<bool> regularized_;
      Vector t_, diff_, uc_, scales_, first_, best_, cand_, found_, q_, local_scales_, local_start_, local_best_;
      std::vector<Block> local_blocks_;
    };
  } // namespace cone
} // namespace multibody_sim
