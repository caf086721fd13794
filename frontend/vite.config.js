import { resolve } from 'node:path';
import { defineConfig } from 'vite';

// Multi-page build: library search, tablet page + viewer, staff pages. The backend serves
// frontend/dist at / and the API at /api/v1; in development Vite proxies /api to it.
export default defineConfig({
  base: './',
  build: {
    outDir: 'dist',
    emptyOutDir: true,
    sourcemap: true,
    chunkSizeWarningLimit: 1000,
    rollupOptions: {
      input: {
        index: resolve(import.meta.dirname, 'index.html'),
        tablet: resolve(import.meta.dirname, 'tablet.html'),
        staff: resolve(import.meta.dirname, 'staff.html'),
      },
    },
  },
  server: {
    proxy: { '/api': process.env.HAMMURABI_API ?? 'http://127.0.0.1:8000' },
  },
  test: {
    include: ['tests/unit/**/*.test.js'],
    environment: 'node',
  },
});
