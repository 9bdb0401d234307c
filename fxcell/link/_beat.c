/* fxcell.link._beat: the cell's beats to the link process from a thread without the GIL
 * (hatch_build.py builds it; fxcell.link.beats is its Python face and fallback).
 *
 * While a trajectory runs, the cell process beats on a channel of its own and the link
 * process brakes when the beats stop (fxcell.link.process). A Python thread needs the GIL
 * for every beat: when the thread holding it is preempted (a normal-priority thread on a
 * busy machine) or sits in a long C call, beats stop although the process is alive, and a
 * healthy move is braked. This thread never takes the GIL. It beats every `period` while
 * the running flag is set and the event loop has said it ran within `stall_after`; a
 * frozen process (SIGSTOP, a swap storm) freezes it with the rest, so the link still sees
 * a frozen cell within its timeout.
 */
#define PY_SSIZE_T_CLEAN
#include <Python.h>
#include <errno.h>
#include <poll.h>
#include <pthread.h>
#include <sched.h>
#include <signal.h>
#include <fcntl.h>
#include <stdatomic.h>
#include <sys/socket.h>
#include <time.h>
#include <unistd.h>

#ifdef MSG_NOSIGNAL
#define SEND_FLAGS MSG_NOSIGNAL
#else
#define SEND_FLAGS 0 /* Python ignores SIGPIPE */
#endif

typedef struct {
    PyObject_HEAD
    int fd;          /* the beat channel (the caller owns it and closes it after stop) */
    int stop_fd[2];  /* a pipe: readable once stop() asks the thread to end */
    int priority;    /* SCHED_FIFO priority asked for the thread; 0: normal scheduling */
    long long period_ns, stall_ns;
    _Atomic long long loop_ran_ns;
    _Atomic int running;
    _Atomic int realtime;  /* whether the thread got SCHED_FIFO (-1: not known yet) */
    int started;
    pthread_t thread;
} Beater;

static long long now_ns(void) {
    struct timespec t;
    clock_gettime(CLOCK_MONOTONIC, &t);  /* Python's time.monotonic() clock */
    return (long long)t.tv_sec * 1000000000LL + t.tv_nsec;
}

static void *beat(void *arg) {
    Beater *self = (Beater *)arg;
    int realtime = 0;
    if (self->priority > 0) {
        struct sched_param param = {.sched_priority = self->priority};
        realtime = pthread_setschedparam(pthread_self(), SCHED_FIFO, &param) == 0;
    }
    atomic_store(&self->realtime, realtime);
#ifdef __linux__
    pthread_setname_np(pthread_self(), "fxcell beats");
#endif
    struct pollfd stop = {.fd = self->stop_fd[0], .events = POLLIN};
    int period_ms = (int)(self->period_ns / 1000000LL);
    for (;;) {
        int ready = poll(&stop, 1, period_ms > 0 ? period_ms : 1);
        if (ready != 0) {
            if (ready < 0 && errno == EINTR) continue;
            return NULL; /* asked to stop (or poll failed) */
        }
        if (!atomic_load(&self->running)) continue;
        if (now_ns() - atomic_load(&self->loop_ran_ns) >= self->stall_ns) continue;
        if (send(self->fd, "b", 1, MSG_DONTWAIT | SEND_FLAGS) < 0 && errno != EAGAIN &&
            errno != EWOULDBLOCK && errno != EINTR && errno != ENOBUFS)
            return NULL; /* the link process is gone */
    }
}

static int Beater_init(Beater *self, PyObject *args, PyObject *kwds) {
    static char *kwlist[] = {"fd", "period", "stall_after", "priority", NULL};
    int fd, priority;
    double period, stall_after;
    if (self->started) {
        PyErr_SetString(PyExc_RuntimeError, "Beater is already initialised");
        return -1;
    }
    if (!PyArg_ParseTupleAndKeywords(args, kwds, "iddi", kwlist, &fd, &period, &stall_after,
                                     &priority))
        return -1;
    if (!(period > 0.0 && period < 10.0) || !(stall_after > 0.0 && stall_after < 3600.0)) {
        PyErr_SetString(PyExc_ValueError, "period and stall_after must be positive seconds");
        return -1;
    }
    self->fd = fd;
    self->priority = priority;
    self->period_ns = (long long)(period * 1e9);
    self->stall_ns = (long long)(stall_after * 1e9);
    atomic_store(&self->loop_ran_ns, now_ns());
    atomic_store(&self->running, 0);
    atomic_store(&self->realtime, -1);
    if (pipe(self->stop_fd) < 0) {
        PyErr_SetFromErrno(PyExc_OSError);
        return -1;
    }
    fcntl(self->stop_fd[0], F_SETFD, FD_CLOEXEC);
    fcntl(self->stop_fd[1], F_SETFD, FD_CLOEXEC);
    /* the thread takes no signal: they stay with Python's threads */
    sigset_t all, old;
    sigfillset(&all);
    pthread_sigmask(SIG_BLOCK, &all, &old);
    int failed = pthread_create(&self->thread, NULL, beat, self);
    pthread_sigmask(SIG_SETMASK, &old, NULL);
    if (failed) {
        close(self->stop_fd[0]);
        close(self->stop_fd[1]);
        errno = failed;
        PyErr_SetFromErrno(PyExc_OSError);
        return -1;
    }
    self->started = 1;
    return 0;
}

static void stop_thread(Beater *self) {
    if (!self->started) return;
    self->started = 0;
    ssize_t written = write(self->stop_fd[1], "x", 1);
    (void)written; /* an empty pipe takes one byte */
    pthread_join(self->thread, NULL); /* within microseconds: the thread waits in poll */
    close(self->stop_fd[0]);
    close(self->stop_fd[1]);
}

static PyObject *Beater_stop(Beater *self, PyObject *Py_UNUSED(ignored)) {
    Py_BEGIN_ALLOW_THREADS
    stop_thread(self);
    Py_END_ALLOW_THREADS
    Py_RETURN_NONE;
}

static PyObject *Beater_loop_ran(Beater *self, PyObject *Py_UNUSED(ignored)) {
    atomic_store(&self->loop_ran_ns, now_ns());
    Py_RETURN_NONE;
}

static PyObject *Beater_set_running(Beater *self, PyObject *arg) {
    int on = PyObject_IsTrue(arg);
    if (on < 0) return NULL;
    atomic_store(&self->running, on);
    Py_RETURN_NONE;
}

static PyObject *Beater_realtime(Beater *self, void *Py_UNUSED(closure)) {
    int realtime = atomic_load(&self->realtime);
    if (realtime < 0) Py_RETURN_NONE;
    return PyBool_FromLong(realtime);
}

static void Beater_dealloc(Beater *self) {
    stop_thread(self);
    Py_TYPE(self)->tp_free((PyObject *)self);
}

static PyMethodDef Beater_methods[] = {
    {"loop_ran", (PyCFunction)Beater_loop_ran, METH_NOARGS,
     "Say that the event loop ran now."},
    {"set_running", (PyCFunction)Beater_set_running, METH_O,
     "Beat (True) or not (False): whether a trajectory runs."},
    {"stop", (PyCFunction)Beater_stop, METH_NOARGS,
     "End the thread (at once; idempotent). The channel stays open."},
    {NULL, NULL, 0, NULL},
};

static PyGetSetDef Beater_getset[] = {
    {"realtime", (getter)Beater_realtime, NULL,
     "Whether the thread runs SCHED_FIFO (None until it has asked).", NULL},
    {NULL, NULL, NULL, NULL, NULL},
};

static PyTypeObject BeaterType = {
    PyVarObject_HEAD_INIT(NULL, 0)
    .tp_name = "fxcell.link._beat.Beater",
    .tp_doc = "A thread that beats on a channel without taking the GIL.",
    .tp_basicsize = sizeof(Beater),
    .tp_flags = Py_TPFLAGS_DEFAULT,
    .tp_new = PyType_GenericNew,
    .tp_init = (initproc)Beater_init,
    .tp_dealloc = (destructor)Beater_dealloc,
    .tp_methods = Beater_methods,
    .tp_getset = Beater_getset,
};

static struct PyModuleDef module = {
    PyModuleDef_HEAD_INIT,
    .m_name = "_beat",
    .m_doc = "The cell's beats to the link process, without the GIL.",
    .m_size = -1,
};

PyMODINIT_FUNC PyInit__beat(void) {
    if (PyType_Ready(&BeaterType) < 0) return NULL;
    PyObject *m = PyModule_Create(&module);
    if (m == NULL) return NULL;
    Py_INCREF(&BeaterType);
    if (PyModule_AddObject(m, "Beater", (PyObject *)&BeaterType) < 0) {
        Py_DECREF(&BeaterType);
        Py_DECREF(m);
        return NULL;
    }
    return m;
}
